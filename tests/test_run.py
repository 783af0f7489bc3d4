"""``mapfree run`` on a tiny real split: a valid submission, a failure log, and resume after a kill."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mapfree.cli import main
from mapfree.data import Dataset, read_intrinsics, read_poses, write_intrinsics, write_poses
from mapfree.relocalize import read_journal, run_split

METHOD = "sift_emat_sensor"


def _tiny_split(src_root: Path, dst_root: Path, keep: dict[str, int]) -> Path:
    """A val split with the reference and the first ``n`` queries of each scene (images linked, not copied)."""
    for name, n in keep.items():
        src, dst = src_root / "val" / name, dst_root / "val" / name
        poses = read_poses(src / "poses.txt")
        names = poses.names[: n + 1]
        intr = read_intrinsics(src / "intrinsics.txt")
        dst.mkdir(parents=True)
        write_intrinsics(dst / "intrinsics.txt", {k: intr[k] for k in names})
        write_poses(dst / "poses.txt", names, [poses.pose(i) for i in range(len(names))])
        for k in names:
            (dst / k).parent.mkdir(exist_ok=True)
            for f in (src / k).parent.glob(Path(k).stem + ".*"):
                os.symlink(f, (dst / k).parent / f.name)
    return dst_root


@pytest.fixture(scope="module")
def tiny(realmini, tmp_path_factory) -> Path:
    return _tiny_split(realmini, tmp_path_factory.mktemp("tiny"), {"s00000": 11, "s00003": 6})


def _read_zip(path: Path) -> dict[str, list[list[str]]]:
    with zipfile.ZipFile(path) as z:
        return {n: [ln.split() for ln in z.read(n).decode().splitlines() if ln.strip()] for n in z.namelist()}


def test_run_writes_valid_submission_and_failure_log(tiny, tmp_path):
    out = tmp_path / "sub.zip"
    res = run_split(tiny, "val", METHOD, out, progress=False)
    assert res.computed == 3 + 2 and res.skipped == 0  # scored = every 5th of 12 and of 7 lines
    files = _read_zip(out)
    assert set(files) == {"pose_s00000.txt", "pose_s00003.txt"}
    assert len(files["pose_s00000.txt"]) >= 2 and files["pose_s00003.txt"] == []  # s00003 has no depth
    for line in files["pose_s00000.txt"]:
        assert len(line) == 9 and all(np.isfinite(float(v)) for v in line[1:]) and float(line[8]) >= 0
    failures = [json.loads(x) for x in res.failures.read_text().splitlines()]
    scored3 = [f.name for f in Dataset(tiny).scene("val", "s00003").scored_queries()]
    assert len(scored3) == 2
    assert [f["frame"] for f in failures if f["scene"] == "s00003"] == scored3
    assert all("depth" in f["reason"] for f in failures if f["scene"] == "s00003")
    assert res.estimated + res.failed == 5
    from mapfree.benchmark import evaluate

    metrics = evaluate(out, tiny, "val").metrics
    assert 0 <= metrics["AUC @ VCRE < 90px"] <= 1 and metrics["Estimates for % of frames"] < 100
    # Same output again without --resume: refused rather than silently discarding results.
    with pytest.raises(FileExistsError, match="resume"):
        run_split(tiny, "val", METHOD, out, progress=False)
    with pytest.raises(ValueError, match="method"):
        run_split(tiny, "val", "sift_pnp_sensor", out, progress=False, resume=True)
    # Resuming a finished run recomputes nothing and can re-rank with another confidence.
    again = run_split(tiny, "val", METHOD, out, progress=False, resume=True, confidence="confidence_score")
    assert again.computed == 0 and again.skipped == 5 and again.estimated == res.estimated


def test_journal_records_give_back_the_lines_written(tiny, tmp_path):
    """The journal's records (``Journal.read``) are its lines: written again they are the same bytes, their poses
    are the submission's and their failures the failure log's; a line of an older journal reads with defaults."""
    from mapfree.relocalize.journal import FrameRecord, Journal, rewrite_journal

    out = tmp_path / "sub.zip"
    run_split(tiny, "val", METHOD, out, progress=False)
    path = out.with_name("sub.journal.jsonl")
    journal = Journal.read(path)
    header, lines = read_journal(path)
    assert journal.header is not None and journal.header.to_json() == header and journal.torn == 0
    assert [r.to_json() for r in journal.frames] == lines and len(lines) == 5
    copy = tmp_path / "copy.jsonl"
    rewrite_journal(copy, journal.header, journal.frames)
    assert copy.read_bytes() == path.read_bytes()
    submitted = {(scene, row[0]): row[1:] for scene, rows in _read_zip(out).items() for row in rows}
    ok = [r for r in journal.frames if r.ok]
    assert ok and all(r.signals.n_matches for r in ok)
    for r in ok:
        row = submitted[(f"pose_{r.scene}.txt", r.frame)]
        assert np.allclose([float(v) for v in row[:7]], [*r.q, *r.t], atol=1e-6)
        assert float(row[7]) == pytest.approx(r.score(None), rel=1e-5)
    failures = [json.loads(x) for x in out.with_name("sub.failures.jsonl").read_text().splitlines()]
    assert failures == [{"scene": r.scene, "frame": r.frame, "reason": r.reason} for r in journal.frames if not r.ok]
    old = FrameRecord.from_json({"kind": "frame", "scene": "s00000", "frame": "seq1/frame_00000.jpg", "ok": False})
    assert (old.reason, old.q, old.p_correct, old.to_json()["signals"]) == ("", None, None, {})


@pytest.mark.slow
def test_resume_after_kill_loses_and_recomputes_nothing(tiny, tmp_path):
    out = tmp_path / "killed" / "sub.zip"
    journal = out.with_name("sub.journal.jsonl")
    cmd = [
        sys.executable,
        "-m",
        "mapfree",
        "run",
        str(tiny),
        "--split",
        "val",
        "--method",
        METHOD,
        "-o",
        str(out),
        "--all-frames",
        "--workers",
        "2",
        "--no-progress",
    ]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 90
    try:
        while time.time() < deadline and proc.poll() is None:
            if journal.is_file() and len(read_journal(journal)[1]) >= 4:
                break
            time.sleep(0.05)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # the whole run, workers included
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, f"run finished before it could be killed: {proc.stderr.read()}"
    before = read_journal(journal)[1]
    total = 11 + 6
    assert 4 <= len(before) < total and not out.exists()

    res = run_split(tiny, "val", METHOD, out, all_frames=True, resume=True, progress=False)
    after = read_journal(journal)[1]
    keys = [(r["scene"], r["frame"]) for r in after]
    assert len(keys) == len(set(keys)) == total  # every frame once: nothing lost, nothing done twice
    assert res.skipped == len(before) and res.computed == total - len(before)
    assert after[: len(before)] == before  # the results written before the kill are kept as they were
    sub = _read_zip(out)
    assert len(sub["pose_s00000.txt"]) == sum(r["ok"] for r in after if r["scene"] == "s00000")


@pytest.mark.slow
def test_ctrl_c_with_workers_stops_at_once_and_resumes(realmini, tmp_path):
    """Ctrl-C (SIGINT to the whole foreground group, as a terminal sends it; twice, as impatient users do) during
    ``run --workers 2``: the run stops after the frames in flight, starts no queued scene, says how to resume, and
    --resume finishes it. Before, the pool kept running every queued scene to its end after the interrupt, and a
    second Ctrl-C hung the exit on idle workers."""
    root = _tiny_split(realmini, tmp_path / "data", {"s00000": 10, "s00001": 10, "s00002": 10})
    out = tmp_path / "sub.zip"
    journal = out.with_name("sub.journal.jsonl")
    cmd = [
        sys.executable,
        "-m",
        "mapfree",
        "run",
        str(root),
        "--split",
        "val",
        "--method",
        METHOD,
        "-o",
        str(out),
        "--all-frames",
        "--workers",
        "2",
        "--no-progress",
    ]
    proc = subprocess.Popen(
        cmd,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        text=True,
    )
    deadline = time.time() + 90
    while time.time() < deadline and proc.poll() is None and len(read_journal(journal)[1]) < 2:
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGINT)
    time.sleep(0.3)
    os.killpg(proc.pid, signal.SIGINT)
    try:
        err = proc.communicate(timeout=30)[1]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "--resume" in err and "Traceback" not in err, err
    before = read_journal(journal)[1]
    assert len({r["scene"] for r in before}) <= 2, "a queued scene started after Ctrl-C"
    assert 2 <= len(before) < 30 and not out.exists()
    res = run_split(root, "val", METHOD, out, all_frames=True, resume=True, workers=2, progress=False)
    keys = [(r["scene"], r["frame"]) for r in read_journal(journal)[1]]
    assert len(keys) == len(set(keys)) == 30 and res.skipped == len(before)


def test_depth_suffix_typo_is_refused_before_any_work(realmini, tmp_path, capsys):
    """``sift_emat_sensr``: no reference of the split has a ``.sensr.png`` map, so the run stops at once naming the
    suffixes that exist, instead of writing a submission where every frame failed (and exiting 0)."""
    out = tmp_path / "sub.zip"
    with pytest.raises(ValueError, match=r"\*\.sensr\.png.*suffixes there: sensor"):
        run_split(realmini, "val", "sift_emat_sensr", out, progress=False)
    assert main(["run", str(realmini), "--method", "sift_pnp_sensr", "-o", str(out), "--no-progress"]) == 1
    assert "sensor" in capsys.readouterr().err and not out.exists()


def test_cli_relocalize_json_and_viz(realmini, tmp_path, capsys):
    scene = realmini / "val" / "s00000"
    png = tmp_path / "viz.png"
    rc = main(
        [
            "relocalize",
            str(scene / "seq0/frame_00000.jpg"),
            str(scene / "seq1/frame_00010.jpg"),
            "--method",
            METHOD,
            "--gt-pose",
            "auto",
            "--viz",
            str(png),
        ]
    )
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["ok"] and png.is_file()
    assert out["error"]["translation_m"] < 0.25 and out["error"]["rotation_deg"] < 5
    assert set(out["timings"]) >= {"match", "depth", "solve"} and len(out["q_wxyz"]) == 4

    K = "495.57,495.48,269.5,169.19"
    rc = main(
        [
            "relocalize",
            str(scene / "seq0/frame_00000.jpg"),
            str(scene / "seq0/frame_00000.jpg"),
            "--method",
            METHOD,
            "--K-ref",
            K,
            "--K-query",
            K,
        ]
    )
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["ok"] and np.allclose(out["t"], 0)  # the reference itself: taken from there

    rc = main(["relocalize", str(scene / "seq0/frame_00000.jpg"), str(tmp_path / "missing.jpg"), "--method", METHOD])
    assert rc == 1 and "missing.jpg" in capsys.readouterr().err


def test_cli_relocalize_bad_intrinsics_flag_is_named(realmini, capsys):
    scene = realmini / "val" / "s00000"
    ref, q = str(scene / "seq0/frame_00000.jpg"), str(scene / "seq1/frame_00010.jpg")
    assert main(["relocalize", ref, q, "--K-ref", "500,500,270,180", "--K-query", "500,500"]) == 1
    assert "--K-query: expected 4" in capsys.readouterr().err
    assert main(["relocalize", ref, q, "--K-ref", "0,500,270,180", "--K-query", "500,500,270,180"]) == 1
    assert "--K-ref: focal lengths must be positive" in capsys.readouterr().err


def test_run_evaluate_on_a_test_split_explains_instead_of_crashing(tmp_path, capsys):
    """``run --split test --evaluate``: the test poses are private (all zeros), so the run's JSON is printed, the
    evaluation is refused with a pointer to ``mapfree evaluate --gt-root``, exit 2; before, a traceback."""
    root = tmp_path / "data"
    assert (
        main(
            [
                "synth",
                str(root),
                "--split",
                "test",
                "--scenes",
                "1",
                "--queries",
                "5",
                "--size",
                "240x320",
                "--no-mono",
                "--quiet",
            ]
        )
        == 0
    )
    capsys.readouterr()
    out = tmp_path / "t.zip"
    assert (
        main(
            [
                "run",
                str(root),
                "--split",
                "test",
                "--method",
                "sift_pnp_sensor",
                "-o",
                str(out),
                "--no-progress",
                "--evaluate",
                "--json",
            ]
        )
        == 1
    )
    res = capsys.readouterr()
    assert json.loads(res.out)["computed"] == 1 and out.is_file()
    assert "--gt-root" in res.err and "Traceback" not in res.err


def test_a_stop_asked_during_a_frame_keeps_that_frame(tiny, tmp_path, monkeypatch):
    """A pool worker asked to stop (Ctrl-C in the parent) while it computes a frame journals that frame and starts
    no other, nor a scene handed to it afterwards: the work in flight is kept for --resume. Before, the finished
    estimate was thrown away."""
    import threading

    from mapfree.methods import get
    from mapfree.relocalize import run as run_mod
    from mapfree.relocalize import scenes

    stop, estimates = threading.Event(), scenes.estimates

    def interrupted(*args, **kwargs):
        for est in estimates(*args, **kwargs):
            stop.set()  # Ctrl-C arrives while this frame is computed
            yield est

    monkeypatch.setattr(run_mod, "_STOP", stop)
    monkeypatch.setattr(scenes, "estimates", interrupted)
    journal = tmp_path / "j.jsonl"
    journal.write_text("")
    method, frames = get(METHOD), [f.name for f in Dataset(tiny).scene("val", "s00003").scored_queries()]
    assert len(frames) >= 2
    run_mod._run_scene(method, str(tiny / "val" / "s00003"), frames, str(journal))
    assert [r["frame"] for r in read_journal(journal)[1]] == frames[:1]
    assert run_mod._run_scene(method, str(tiny / "val" / "s00000"), frames, str(journal)) == 0
    assert len(read_journal(journal)[1]) == 1


def test_refused_run_leaves_an_existing_journal_alone(realmini, tmp_path):
    """Bad data refused up front (here a depth-suffix typo) with --overwrite or --resume: the earlier run's journal
    is kept byte for byte. Before, the journal was restarted first, so a typo under --overwrite lost it."""
    out = tmp_path / "sub.zip"
    journal = out.with_name("sub.journal.jsonl")
    from mapfree.methods import get

    old = (
        json.dumps({"kind": "header", "version": 1, "method": get("sift_emat_sensr").to_dict()})
        + "\n"
        + json.dumps({"kind": "frame", "scene": "s00000", "frame": "seq1/frame_00000.jpg", "ok": False})
        + "\n"
    )
    journal.write_text(old)
    for flags in ({"overwrite": True}, {"resume": True}):
        with pytest.raises(ValueError, match=r"\*\.sensr\.png"):
            run_split(realmini, "val", "sift_emat_sensr", out, progress=False, **flags)
        assert journal.read_text() == old

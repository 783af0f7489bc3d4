"""What the other commands (synth, build, train, check, evaluate, admin) say when something is wrong: one line naming
the flag, the file or the value, the exit status every command uses, and nothing else on the terminal."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from cli_support import one_line as _one_line
from mapfree.cli import main

SYNTH_ARGS = ["--size", "240x320", "--no-mono", "--quiet"]


def test_build_on_an_empty_folder_is_an_error(tmp_path, capsys):
    from mapfree.cli import main

    (tmp_path / "scans").mkdir()
    assert main(["build", str(tmp_path / "scans"), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mapfree build: error:") and "no place folders" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["synth", "ROOT", "--size", "big"],
        ["synth", "ROOT", "--split", "val", "--private-gt", "G"],
        ["build", "SCANS", "--out", "OUT", "--matcher", "nope"],
        ["build", "SCANS", "--out", "OUT", "--workers", "0"],
    ],
)
def test_synth_and_build_flag_checks_say_error_like_every_command(argv, tmp_path, capsys):
    from mapfree.cli import main

    argv = [str(tmp_path / a) if a.isupper() else a for a in argv]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"mapfree {argv[0]}: error: ") and err.count("\n") == 1


@pytest.mark.parametrize(
    "argv",
    [["nosuch"], ["R6D_t_cpu_synth", "--set", "model.rotation=euler"], ["R6D_t_cpu_synth", "--resume", "nosuch.ckpt"]],
)
def test_train_argument_errors_come_before_lightning_is_imported(argv, tmp_path):
    """A typo in `mapfree train`'s command line once waited for Lightning (seconds) and its banner lines."""
    import os
    import subprocess
    import sys

    probe = (
        "import sys\nfrom mapfree.cli import main\ncode = main(sys.argv[1:])\n"
        "print('LOADED' if any(m in sys.modules for m in ('pytorch_lightning', 'lightning')) else 'CLEAN', code)"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    p = subprocess.run(
        [sys.executable, "-c", probe, "train", *argv, "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert p.stdout.split() == ["CLEAN", "1"], (p.stdout, p.stderr)
    assert p.stderr.startswith("mapfree train: error:") and "Traceback" not in p.stderr


@pytest.mark.slow
def test_train_prints_no_lightning_banner(tmp_path):
    """`mapfree train` printed Lightning's accelerator banner, a tip and two warnings that ask nothing of the user
    before its own output; its real warnings (no validation ran here) stay."""
    import os
    import subprocess
    import sys

    from mapfree.cli import main

    for split in ("train", "val"):
        assert (
            main(["synth", str(tmp_path / "data"), "--split", split, "--scenes", "1", "--queries", "10", *SYNTH_ARGS])
            == 0
        )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapfree",
            "train",
            "R6D_t_cpu_synth",
            "--data",
            str(tmp_path / "data"),
            "--out",
            str(tmp_path / "run"),
            "--max-steps",
            "1",
            "--set",
            "data.batch_size=2",
            "--no-progress",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert p.returncode == 0, p.stderr
    for noise in ("GPU available", "TPU available", "Tip:", "LeafSpec", "in eval mode"):
        assert noise not in p.stderr, p.stderr
    assert (tmp_path / "run" / "checkpoints" / "last.ckpt").is_file()


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


def test_negative_counts_are_refused(synth, tmp_path, capfd):
    """`evaluate --worst -1` showed "the worst 3 of 4" (a Python slice); `check --max-problems -1` likewise."""
    from mapfree.benchmark import write_submission

    sub = tmp_path / "e.zip"
    write_submission(sub, {})
    assert (
        main(["evaluate", str(sub), "--dataset", str(synth), "--html", str(tmp_path / "r.html"), "--worst", "-1"]) == 1
    )
    assert _one_line(capfd)[1] == "mapfree evaluate: error: --worst must be >= 0, got -1"
    assert main(["check", str(synth), "--subset", "--max-problems", "-1"]) == 1
    assert _one_line(capfd)[1] == "mapfree check: error: --max-problems must be >= 0, got -1"
    assert not (tmp_path / "r.html").exists()


def test_small_wording_items(synth, tmp_path, capfd):
    """check FILE.zip said "no such folder"; --gt-root nogt was called the dataset root; "1 scenes"."""
    from mapfree.benchmark import write_submission

    sub = tmp_path / "e.zip"
    write_submission(sub, {})
    assert main(["check", str(sub)]) == 1
    assert _one_line(capfd)[1] == (
        f"mapfree check: error: {sub}: a ZIP file, not a dataset folder: unzip it and check the folder it makes"
    )
    assert main(["evaluate", str(sub), "--dataset", str(synth), "--gt-root", str(tmp_path / "nogt")]) == 1
    assert _one_line(capfd)[1] == (
        f"mapfree evaluate: error: ground-truth root {tmp_path / 'nogt'} (--gt-root) does not exist"
    )
    assert (
        main(
            [
                "run",
                str(synth),
                "--method",
                "sift_pnp_sensor",
                "-o",
                str(tmp_path / "one.zip"),
                "--scenes",
                "s00001",
                "--no-progress",
            ]
        )
        == 0
    )
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
    p = subprocess.run(
        ["bash", "-c", f"{sys.executable} -m mapfree run --list-methods | true; echo ${{PIPESTATUS[0]}}"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert p.stdout.strip() == "141" and p.stderr == "", p.stderr

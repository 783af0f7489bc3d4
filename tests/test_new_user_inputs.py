"""Inputs a new user meets in the third hour, each run as its own process as the user runs it: a 108-megapixel
photo, output names that are not valid UTF-8, a full disk, a journal cut mid-line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cli_support import mapfree_process, query_pair

#: The child runs mapfree under an address-space cap (a huge photo decoded and matched at its size fails at once
#: there instead of taking the machine's memory) and prints its peak resident memory, MB, on its last line.
CAPPED = """\
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
from mapfree.cli import main
code = main(sys.argv[1:])
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024)
sys.exit(code)
"""


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}


@pytest.fixture(scope="module")
def big_jpeg(tmp_path_factory) -> Path:
    """A 12000x9000 (108 MP) JPEG of one colour: 1.7 MB on disk, 324 MB decoded."""
    path = tmp_path_factory.mktemp("big") / "phone_108mp.jpg"
    assert cv2.imwrite(str(path), np.full((9000, 12000, 3), 120, np.uint8))
    return path


def test_a_photo_over_the_pixel_budget_is_refused_from_its_header_in_one_line(synth, big_jpeg):
    """It grew to 20.8 GB in SIFT at its size until the OOM killer came; now it is refused before decoding."""
    a, _ = query_pair(synth)

    def run(command: str, image: Path, *rest: str) -> tuple[subprocess.CompletedProcess, int]:
        args = [command, a, str(image), *rest]
        p = subprocess.run(
            [sys.executable, "-c", CAPPED, *args], capture_output=True, text=True, env=_env(), timeout=120
        )
        return p, int(p.stdout.splitlines()[-1])

    for command, *rest in (
        ["match"],
        ["relocalize", "--method", "sift_emat_none", "--K-query", "9000,9000,6000,4500"],
    ):
        p, peak = run(command, big_jpeg, *rest)
        assert p.returncode == 1 and p.stderr.splitlines() == [
            f"mapfree {command}: error: {big_jpeg}: 12000x9000 is 108.0 megapixels, over the 50-megapixel budget: "
            "downscale it (the intrinsics with it), or raise $MAPFREE_MAX_PIXELS"
        ], p.stderr
        _, baseline = run(command, big_jpeg.with_name("nosuch.jpg"), *rest)  # refused at the same step
        assert peak < baseline + 100, (peak, baseline)  # MB: decoded, it would be 324 MB more


def test_the_pixel_budget_is_one_variable_and_pillows_bomb_warning_never_shows(big_jpeg, monkeypatch):
    from mapfree.data import read_image
    from mapfree.data.io import MAX_PIXELS, image_size_problem

    assert MAX_PIXELS == 50_000_000
    data = big_jpeg.read_bytes()
    monkeypatch.setenv("MAPFREE_MAX_PIXELS", "200000000")
    assert image_size_problem(data) is None  # 108 MP: over Pillow's warning threshold, but it says nothing
    monkeypatch.setenv("MAPFREE_MAX_PIXELS", "1000")
    with pytest.raises(ValueError, match=r"over the 0.001-megapixel budget"):
        read_image(big_jpeg)


def test_a_one_pixel_image_is_refused_naming_the_file(synth, tmp_path, capfd):
    from mapfree.cli import main

    tiny = tmp_path / "tiny.png"
    cv2.imwrite(str(tiny), np.full((1, 1, 3), 90, np.uint8))
    a, _ = query_pair(synth)
    assert main(["match", a, str(tiny)]) == 1
    assert capfd.readouterr().err.splitlines() == [
        f"mapfree match: error: {tiny}: 1x1 pixels: too small (both sides must be >= 8)"
    ]


def test_output_names_that_are_not_utf8_are_written_not_a_segfault(synth, tmp_path):
    """OpenCV's imwrite crashed (exit 139, nothing printed) on such names; images are now written by Python."""
    a, b = query_pair(synth)
    viz = os.fsencode(tmp_path) + b"/out_\xff/m.png"
    p = subprocess.run(
        [sys.executable, "-m", "mapfree", "match", a, b, "--viz", viz], capture_output=True, env=_env(), timeout=120
    )
    assert p.returncode == 0, p.stderr
    assert cv2.imdecode(np.fromfile(viz, np.uint8), cv2.IMREAD_COLOR).shape[1] == 2 * 240  # side by side
    root = os.fsencode(tmp_path) + b"/syn_\xff"
    p = subprocess.run(
        [sys.executable, "-m", "mapfree", "synth", root, "--scenes", "1", "--queries", "2", "--size", "64x48"]
        + ["--no-mono", "--quiet"],
        capture_output=True,
        env=_env(),
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    photo = root + b"/val/s00000/seq0/frame_00000.jpg"
    assert cv2.imdecode(np.fromfile(photo, np.uint8), cv2.IMREAD_COLOR).shape == (48, 64, 3)


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_a_full_disk_is_named_with_the_output_it_stopped(synth, tmp_path):
    """``No space left on device`` alone said nothing of which output; /dev/full answers every write with it."""
    a, b = query_pair(synth)
    for flag, name in (("-o", "m.npz"), ("--viz", "m.png")):
        out = tmp_path / name
        out.symlink_to("/dev/full")
        p = mapfree_process("match", a, b, flag, out)
        assert p.returncode == 1 and p.stderr.splitlines() == [f"mapfree match: error: {out}: no space left on device"]
    journal = tmp_path / "run" / "sub.journal.jsonl"
    journal.parent.mkdir()
    journal.symlink_to("/dev/full")
    p = mapfree_process(
        "run", synth, "--method", "sift_pnp_sensor", "-o", tmp_path / "run" / "sub.zip", "--no-progress"
    )
    assert p.returncode == 1 and p.stderr.splitlines() == [f"mapfree run: error: {journal}: no space left on device"]


def test_a_resumed_journal_cut_mid_line_says_how_many_lines_it_lost(synth, tmp_path):
    out = tmp_path / "sub.zip"
    args = ("run", synth, "--method", "sift_pnp_sensor", "-o", out, "--no-progress", "--scenes", "s00000")
    assert mapfree_process(*args).returncode == 0
    journal = tmp_path / "sub.journal.jsonl"
    whole = journal.read_bytes()
    journal.write_bytes(whole[: whole.rindex(b"\n", 0, len(whole) - 1) + 20])  # the last record cut after 19 bytes
    p = mapfree_process(*args, "--resume")
    assert p.returncode == 0 and p.stderr.splitlines() == [
        f"mapfree run: {journal}: 1 line(s) cut mid-write (a kill or a full disk) dropped; their frames were "
        "computed again"
    ], p.stderr
    assert "1 computed" in p.stdout and journal.read_bytes().count(b"\n") == whole.count(b"\n")

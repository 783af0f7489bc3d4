"""mapfree check: a complete folder passes, and each kind of damage to a copy is named with its file (and line)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from mapfree.cli import main
from mapfree.data import check_dataset
from mapfree.data.check import RELEASE
from mapfree.data.synth import SynthOptions, generate


def _check(capsys, *argv: str) -> tuple[int, str]:
    code = main(["check", *argv])
    return code, capsys.readouterr().out


@pytest.fixture
def copy(realmini: Path, tmp_path: Path) -> Path:
    """Two realmini-dev scenes copied to a scratch root, to damage."""
    for name in ("s00000", "s00001"):
        shutil.copytree(realmini / "val" / name, tmp_path / "val" / name)
    return tmp_path


def test_realmini_passes_as_a_subset_and_reports_frames_and_depth(realmini, capsys):
    code, out = _check(capsys, str(realmini), "--subset")
    assert code == 0, out
    assert "OK: nothing missing or unreadable" in out
    report = check_dataset(realmini, subset=True)
    (val,) = report.splits
    frames = sum(
        len((realmini / "val" / s / "intrinsics.txt").read_text().split("\n")) - 1
        for s in ("s00000", "s00001", "s00002", "s00003")
    )
    assert (val.split, val.scenes, val.frames, val.images_checked) == ("val", 4, frames, frames)
    assert val.depth == {"sensor": len(list((realmini / "val").glob("s*/seq*/*.sensor.png")))}
    # the same in parallel worker processes, and with every image and depth map decoded
    assert check_dataset(realmini, subset=True, workers=2).to_dict() == report.to_dict()
    assert check_dataset(realmini, subset=True, deep=True).ok


def test_against_the_release_realmini_lacks_scenes_and_splits(realmini, capsys):
    code, out = _check(capsys, str(realmini), "--json")
    assert code == 1
    problems = json.loads(out)["splits"]
    by = {s["split"]: s for s in problems}
    assert by["train"]["expected"] == 460 and by["test"]["expected"] == 130 and by["val"]["expected"] == 65
    assert any("split folder missing" in p for p in by["train"]["problems"])
    assert any("65 of the release's 65 scenes missing: s00460" in p for p in by["val"]["problems"])
    assert any(p.endswith("val/s00000: not a val scene of the release (s00460–s00524)") for p in by["val"]["problems"])


def test_a_missing_scene_of_the_release_is_named(realmini, tmp_path, capsys):
    val = tmp_path / "val"
    val.mkdir()
    for i in list(RELEASE["val"])[:-1]:  # every val scene but the last (s00524), each a link to one real scene
        (val / f"s{i:05d}").symlink_to(realmini / "val" / "s00001", target_is_directory=True)
    code, out = _check(capsys, str(tmp_path), "--split", "val")
    assert code == 1
    assert f"{val}: 1 of the release's 65 scenes missing: s00524" in out
    assert "64/65" in out
    (val / "s00524").symlink_to(realmini / "val" / "s00001", target_is_directory=True)
    code, out = _check(capsys, str(tmp_path), "--split", "val")
    assert code == 0, out


def test_missing_image_bad_line_and_size_mismatch_are_named(copy, capsys):
    scene = copy / "val" / "s00000"
    query = sorted((scene / "seq1").glob("*.jpg"))[3]
    query.unlink()
    lines = (scene / "poses.txt").read_text().splitlines()
    lines[2] = "seq1/frame_x.jpg 1 0 0"
    (scene / "poses.txt").write_text("\n".join(lines) + "\n")
    intr = (copy / "val" / "s00001" / "intrinsics.txt").read_text().splitlines()
    name, fx, fy, cx, cy, w, h = intr[0].split()
    intr[0] = " ".join([name, fx, fy, cx, cy, str(int(w) + 2), h])
    (copy / "val" / "s00001" / "intrinsics.txt").write_text("\n".join(intr) + "\n")

    code, out = _check(capsys, str(copy), "--subset")
    assert code == 1
    assert f"{query}: listed in intrinsics.txt but missing" in out
    assert f"{scene / 'poses.txt'}:3: expected 8 fields, found 4" in out
    assert f"{copy / 'val/s00001' / name}: image is {w}x{h} but intrinsics.txt says {int(w) + 2}x{h}" in out
    assert "3 problems found" in out


def test_empty_truncated_and_8bit_files_are_named(copy):
    seq1 = copy / "val" / "s00000" / "seq1"
    images = sorted(seq1.glob("*.jpg"))
    images[0].write_bytes(b"")
    data = images[1].read_bytes()
    images[1].write_bytes(data[: len(data) // 2])  # an interrupted download
    depth, other = sorted(seq1.glob("*.sensor.png"))[:2]
    cv2.imwrite(str(depth), np.zeros((8, 8), np.uint8))  # 8-bit, not millimetres
    cv2.imwrite(str(other), np.ones((10, 10), np.uint16))  # another aspect ratio: not this frame's map
    for deep in (False, True):
        found = {p.path: p.reason for p in check_dataset(copy, subset=True, deep=deep).all_problems}
        assert found[str(images[0])] == "empty file"
        assert str(depth) in found and "16-bit" in found[str(depth)]
        assert "another aspect ratio" in found[str(other)]
        if not deep:
            assert found[str(images[1])] == "truncated JPEG (no end-of-image marker)"
    assert check_dataset(copy / "val" / "s00001", subset=True).problems  # not a dataset root: said so


def test_train_split_needs_overlaps(tmp_path, capsys):
    generate(
        tmp_path,
        "train",
        n_scenes=1,
        seed=0,
        progress=False,
        options=SynthOptions(width=120, height=160, texture_size=128, train_frames=3, write_mono=False),
    )
    code, out = _check(capsys, str(tmp_path), "--subset")
    assert code == 0, out
    assert "sensor 6" in out
    overlaps = tmp_path / "train" / "s00000" / "overlaps.npz"
    overlaps.unlink()
    code, out = _check(capsys, str(tmp_path), "--subset")
    assert code == 1 and f"{overlaps}: file not found" in out


def test_test_split_with_hidden_poses_passes_and_the_reference_is_required(tmp_path):
    generate(
        tmp_path,
        "test",
        n_scenes=1,
        n_queries=5,
        seed=0,
        progress=False,
        options=SynthOptions(width=120, height=160, texture_size=128, write_mono=False),
    )
    scene = tmp_path / "test" / "s00000"
    assert set((scene / "poses.txt").read_text().split()[1:8]) == {"0"}  # all-zero lines: hidden ground truth
    assert check_dataset(tmp_path, subset=True).ok
    lines = [ln for ln in (scene / "intrinsics.txt").read_text().splitlines() if not ln.startswith("seq0/")]
    (scene / "intrinsics.txt").write_text("\n".join(lines) + "\n")
    found = [str(p) for p in check_dataset(tmp_path, subset=True).all_problems]
    assert f"{scene / 'intrinsics.txt'}: no reference image seq0/frame_00000.jpg listed" in found


def test_exif_turned_photos_are_checked_as_displayed_in_both_modes(copy):
    from PIL import Image

    seq1 = copy / "val" / "s00000" / "seq1"
    turned, mirrored = sorted(seq1.glob("*.jpg"))[:2]
    for path, orientation in ((turned, 6), (mirrored, 2)):
        upright = np.asarray(Image.open(path).convert("RGB"))
        exif = Image.Exif()
        exif[0x0112] = orientation
        stored = np.rot90(upright, 1) if orientation == 6 else upright  # 6: the stored grid turned back
        Image.fromarray(np.ascontiguousarray(stored)).save(path, exif=exif, quality=95)
    for deep in (False, True):  # the header check agrees with decoding (read_image turns the photo upright)
        found = {p.path: p.reason for p in check_dataset(copy, subset=True, deep=deep).all_problems}
        assert str(turned) not in found, found[str(turned)]
        assert "mirrored" in found[str(mirrored)]


def test_a_bad_workers_value_is_an_error_line_and_status_1_as_in_every_command(realmini, capsys):
    assert main(["check", str(realmini), "--subset", "--workers", "0"]) == 1  # 2 is argparse's own usage errors
    assert capsys.readouterr().err.strip() == "mapfree check: error: --workers must be >= 1"

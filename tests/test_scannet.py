"""ScanNet relative pose: the SuperGlue/LoFTR pair-list reader (a tiny ScanNet-layout folder of real
realmini-dev frames), the pose-AUC report, and ``mapfree scannet``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mapfree.benchmark.relpose import pose_auc, relpose_errors
from mapfree.data import FormatError
from mapfree.data.scannet import read_pairs
from realmini_layouts import realmini_frames, scannet_pairs

PAIRS = [(0, 3), (5, 9), (10, 14), (15, 20)]


@pytest.fixture(scope="module")
def pair_list(realmini, tmp_path_factory):
    return scannet_pairs(realmini, tmp_path_factory.mktemp("scannet"), PAIRS)


def test_reader_pairs_intrinsics_depth(realmini, pair_list):
    _, queries = realmini_frames(realmini)
    pairs = read_pairs(pair_list)
    assert len(pairs) == len(PAIRS) and pairs[0].line == 1
    p = pairs[1]
    i, j = PAIRS[1]
    assert p.frame0.name == f"scene0000_00/color/frame-{i:06d}.jpg"
    assert p.frame0.intrinsics == queries[i].intrinsics  # K from the line, size from the image header
    rel = queries[j].pose @ queries[i].pose.inverse()
    np.testing.assert_allclose(p.T_0to1.R, rel.R, atol=1e-8)
    np.testing.assert_allclose(p.T_0to1.t, rel.t, atol=1e-8)
    assert p.frame1.depth_path("depth").name == f"frame-{j:06d}.png" and p.frame1.has_depth("depth")
    np.testing.assert_allclose(p.frame1.depth("depth"), queries[j].depth("sensor"))


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda f: f[:30], "expected 38 fields"),
        (lambda f: f[:4] + ["x"] + f[5:], "unparseable number"),
        (lambda f: f[:4] + ["nan"] + f[5:], "non-finite"),
        (lambda f: f[:2] + ["1"] + f[3:], "EXIF rotations"),
        (lambda f: f[:22] + ["5"] + f[23:], "T_0to1 is not a rigid transform"),
        (lambda f: f[:4] + ["-3"] + f[5:], "K0 is not a pinhole camera matrix"),
        (lambda f: ["nowhere/color/frame-000001.jpg"] + f[1:], "missing or unreadable"),
    ],
)
def test_reader_names_the_bad_line(pair_list, tmp_path, edit, message):
    lines = pair_list.read_text().splitlines()
    lines.insert(0, "# a comment line is skipped")
    lines[2] = " ".join(edit(lines[2].split()))
    bad = tmp_path / "bad.txt"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(FormatError, match=rf"bad\.txt:3: .*{message}"):
        read_pairs(bad, pair_list.parent)


def test_pose_auc_and_errors():
    # Errors 1°, 3° and one failure: recall 1/3 from 1° and 2/3 from 3°, never 1.
    auc5, auc10, _ = pose_auc(np.array([1.0, 3.0, np.inf]))
    assert auc5 == pytest.approx((0.5 * 1 * 1 / 3 + (1 / 3 + 2 / 3) / 2 * 2 + 2 / 3 * 2) / 5)
    assert auc10 > auc5
    assert pose_auc(np.zeros(4)) == [1.0, 1.0, 1.0]
    R = np.eye(3)[None]
    r, a, m = relpose_errors(R, np.array([[1.0, 0, 0]]), R, np.array([[-2.0, 0, 0]]))
    assert r[0] == 0 and a[0] == 0 and m[0] == pytest.approx(3.0)  # direction error folds the E sign ambiguity


def test_scannet_cli_scores_real_pairs(pair_list, tmp_path, capsys):
    from mapfree.cli import main

    out = tmp_path / "out"
    assert main(["scannet", str(pair_list), "--method", "sift_emat_depth", "--out", str(out), "--no-progress"]) == 0
    assert "AUC @ 20°" in capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    m = rep["metrics"]
    assert (
        m["Pairs"] == len(PAIRS)
        and m["Estimates for % of pairs"] == 1.0
        and m["Metric estimates for % of pairs"] == 1.0
    )
    assert m["AUC @ 20°"] >= m["AUC @ 10°"] >= m["AUC @ 5°"] > 0.3
    assert m["Median translation error (m)"] < 0.1
    assert len(rep["pairs"]) == len(PAIRS) and (out / "pose_error_cdf.png").stat().st_size > 0
    # Without depth the poses have no scale: no metric translation error, the angular scores remain.
    assert (
        main(
            [
                "scannet",
                str(pair_list),
                "--method",
                "sift_emat_none",
                "--out",
                str(tmp_path / "o2"),
                "--no-progress",
                "--limit",
                "2",
            ]
        )
        == 0
    )
    m2 = json.loads((tmp_path / "o2" / "report.json").read_text())["metrics"]
    assert m2["Pairs"] == 2 and m2["Median translation error (m)"] is None and m2["AUC @ 20°"] > 0
    assert main(["scannet", str(tmp_path / "missing.txt"), "--out", str(tmp_path / "o3")]) == 1
    # Ran, but not a single pair estimated (PnP without any depth): exit 3, the report is still written.
    capsys.readouterr()
    assert (
        main(
            [
                "scannet",
                str(pair_list),
                "--method",
                "sift_pnp_none",
                "--out",
                str(tmp_path / "o4"),
                "--no-progress",
                "--limit",
                "1",
            ]
        )
        == 3
    )
    assert "no pair got an estimate" in capsys.readouterr().err and (tmp_path / "o4" / "report.json").is_file()

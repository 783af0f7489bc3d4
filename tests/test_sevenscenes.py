"""7-Scenes: the native-layout reader (on a tiny folder of real realmini-dev frames), the localisation
report, and ``mapfree sevenscenes`` with K = 1 and K = 4 references per scene."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from mapfree.benchmark.localization import localization_report
from mapfree.data import FormatError
from mapfree.data.sevenscenes import SevenScenes, read_matrix_pose
from realmini_layouts import realmini_frames, seven_scenes

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def seven(realmini, tmp_path_factory):
    return seven_scenes(realmini, tmp_path_factory.mktemp("7s") / "7scenes")


def camera(realmini):
    K = realmini_frames(realmini)[0].intrinsics
    return (K.fx, K.fy, K.cx, K.cy)


def test_reader_frames_poses_and_depth(realmini, seven):
    ref, queries = realmini_frames(realmini)
    ds = SevenScenes(seven, camera(realmini))
    assert ds.scene_names() == ["office"]
    sc = ds.scene("office")
    assert sc.sequences("train") == ["seq-01"] and sc.sequences("test") == ["seq-02"]
    train, test = sc.frames("train"), sc.frames("test")
    src = [ref] + queries
    assert len(train) + len(test) == len(src) and len(train) == len(src[::3])
    assert train[0].name == "seq-01/frame-000000.color.png" and train[0].intrinsics.width == 540
    np.testing.assert_allclose(train[1].pose.R, src[3].pose.R, atol=1e-7)  # cam-to-world file -> world-to-cam
    np.testing.assert_allclose(train[1].pose.t, src[3].pose.t, atol=1e-7)
    d = train[1].depth("depth")
    sensor = src[3].depth("sensor")
    assert d.shape == sensor.shape and np.array_equal(d > 0, sensor > 0)  # 65535 read as "no measurement"
    assert np.allclose(d[d > 0], sensor[d > 0])
    assert len(sc.frames("test", stride=4)) == len(test[::4])


def test_reader_names_each_bad_file(realmini, seven, tmp_path):
    import shutil

    root = tmp_path / "bad"
    shutil.copytree(seven, root)
    sc = SevenScenes(root, camera(realmini)).scene("office")
    pose = root / "office/seq-02/frame-000001.pose.txt"
    pose.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(FormatError, match=r"frame-000001\.pose\.txt.*4x4"):
        sc.frames("test")
    pose.write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(FormatError, match="not a rigid transform"):
        read_matrix_pose(pose)
    pose.write_text("1 0 0 x\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(FormatError, match="unparseable"):
        read_matrix_pose(pose)
    (root / "office/TestSplit.txt").write_text("sequence2\nseq 3\n")
    with pytest.raises(FormatError, match=r"TestSplit\.txt:2"):
        sc.sequences("test")
    (root / "office/TestSplit.txt").write_text("sequence7\n")
    with pytest.raises(FormatError, match="seq-07 does not exist"):
        sc.sequences("test")
    (root / "office/TrainSplit.txt").unlink()
    with pytest.raises(FormatError, match="TrainSplit.txt: split file not found"):
        sc.frames("train")
    with pytest.raises(FileNotFoundError, match="no such 7-Scenes scene"):
        SevenScenes(root).scene("chess")


def test_localization_report_counts_failures(realmini, seven):
    sc = SevenScenes(seven, camera(realmini)).scene("office")
    test = sc.frames("test")
    n = len(test)
    q = np.stack([f.pose.qt()[0] for f in test])
    t = np.stack([f.pose.qt()[1] for f in test])
    K = np.array([[f.intrinsics.fx, f.intrinsics.fy, f.intrinsics.cx, f.intrinsics.cy] for f in test])
    q_est, t_est = q.copy(), t.copy()
    t_est[1] += [0.5, 0, 0]  # one frame 50 cm off
    q_est[2] = np.nan  # one frame without estimate
    r = localization_report(
        ["office"] * n, [f.name for f in test], q, t, q_est, t_est, np.ones(n), K, np.full(n, 540), np.full(n, 360)
    )
    assert r.thresholds.vcre == (64.9, 32.4)  # 10 % and 5 % of the 540x360 diagonal
    assert r.metrics["Precision @ VCRE < 64.9px"] == pytest.approx((n - 2) / n)
    assert r.metrics["Estimates for % of frames"] == pytest.approx((n - 1) / n)
    assert r.vcre[1] > 64.9 and r.vcre[0] == pytest.approx(0, abs=1e-6) and np.isnan(r.vcre[2])
    with pytest.raises(ValueError, match="contiguous"):
        localization_report(
            ["a", "b", "a"], ["x"] * 3, q[:3], t[:3], q[:3], t[:3], np.ones(3), K[:3], np.full(3, 540), np.full(3, 360)
        )


@pytest.mark.slow
def test_sevenscenes_cli_more_references_localise_better(realmini, seven, tmp_path, capsys):
    from mapfree.cli import main

    out = tmp_path / "out"
    rc = main(
        [
            "sevenscenes",
            str(seven),
            "--method",
            "sift_pnp_depth",
            "--k",
            "1,4",
            "--mapping-stride",
            "1",
            "--query-stride",
            "2",
            "--intrinsics",
            *map(str, camera(realmini)),
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert rc == 0
    assert "K=4" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    key = "Precision @ VCRE < 64.9px"
    assert summary["K=4"][key] > summary["K=1"][key] and summary["K=4"][key] >= 0.8
    for f in ("compare_precision_ratio.png", "compare_vcre_cdf.png", "K1/report.json", "K4/vcre_cdf.png"):
        assert (out / f).stat().st_size > 0
    frames = json.loads((out / "K4" / "report.json").read_text())["frames"]
    assert len(frames) == len(SevenScenes(seven).scene("office").frames("test", 2))
    img = cv2.imread(str(out / "compare_vcre_cdf.png"))
    assert img is not None and img.std() > 5  # a drawn figure, not a blank canvas
    assert main(["sevenscenes", str(seven), "--k", "0", "--out", str(out)]) == 1


def test_sevenscenes_says_when_k_exceeds_the_mapping_frames(realmini, seven, tmp_path, capsys):
    """--k 10 with the default --mapping-stride 10 on a short scene: the K=10 row is K=1 in truth, and the
    command says so (before, two identical rows and no word why)."""
    from mapfree.cli import main

    n = len(SevenScenes(seven).scene("office").frames("train", 10))
    assert n < 10
    assert (
        main(
            [
                "sevenscenes",
                str(seven),
                "--method",
                "sift_pnp_depth",
                "--k",
                "10",
                "--query-stride",
                "50",
                "--intrinsics",
                *map(str, camera(realmini)),
                "--out",
                str(tmp_path / "o"),
                "--no-plots",
                "--no-progress",
            ]
        )
        == 0
    )
    assert f"office has {n} mapping frame(s) at --mapping-stride 10, so K > {n} uses {n}" in capsys.readouterr().err

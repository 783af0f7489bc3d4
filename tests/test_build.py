"""mapfree build on synthetic raw scans: real pycolmap SfM, metric scale, layout, accuracy, failures, Ray."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("pycolmap")

import contextlib

from mapfree.cli import main as cli_main
from mapfree.data import Dataset, read_overlaps, read_poses
from mapfree.data.synth import SynthOptions
from mapfree.data.synth.scans import ScanOptions, generate_scans
from mapfree.geometry import Pose, backproject, project
from mapfree.scenebuild import BuildOptions, read_correspondences
from mapfree.scenebuild.accuracy import compare_to_truth
from mapfree.scenebuild.inputs import interpolate_track, read_place, read_tum
from mapfree.scenebuild.run import build_all

SMALL = ScanOptions(frames=8, synth=SynthOptions(width=240, height=320, texture_size=256, write_mono=False))


@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scans")
    generate_scans(root, 1, seed=0, options=SMALL, private_gt_dir=root / "gt", progress=False)
    return root


@pytest.fixture(scope="module")
def built(scans, tmp_path_factory) -> tuple[Path, list]:
    out = tmp_path_factory.mktemp("built")
    results = build_all(scans / "scans", out, BuildOptions(split="train", correspondences=True), progress=False)
    return out, results


def test_scans_split_layout(scans):
    place = read_place(scans / "scans" / "s00000")
    assert [s.name for s in place.scans] == ["scan0", "scan1"]
    for scan in place.scans:
        assert len(scan.frames) == 8
        assert all(f.intrinsics is not None and f.device is not None for f in scan.frames)
        assert np.all(np.diff([f.time for f in scan.frames]) > 0)
    # The device track drifts, but only by centimetres over a few metres of walking.
    t, c, _ = read_tum(scans / "scans/s00000/scan0/device_poses.txt")
    assert len(t) == (8 - 1) * SMALL.device_rate + 1
    truth = read_poses(scans / "gt/scans/s00000/scan0/poses.txt")
    dev = np.stack([f.device.center for f in place.scans[0].frames])
    true = np.stack([truth.pose(i).center for i in range(len(truth))])
    d_dev = np.linalg.norm(dev[:, None] - dev[None], axis=-1)
    d_true = np.linalg.norm(true[:, None] - true[None], axis=-1)
    assert 0 < np.abs(d_dev - d_true).max() < 0.1 * d_true.max()


def test_interpolate_track_between_samples():
    R = np.stack([np.eye(3)] * 2)
    poses = interpolate_track(np.array([0.0, 1.0]), np.array([[0.0, 0, 0], [2.0, 0, 0]]), R, np.array([0.25, 2.0]))
    assert np.allclose(poses[0].t, [0.5, 0, 0]) and poses[1] is None
    # Rotations are slerped too: a quarter of a 90-degree turn about z is 22.5 degrees.
    R = np.stack([np.eye(3), cv2.Rodrigues(np.array([0.0, 0.0, np.pi / 2]))[0]])
    mid = interpolate_track(np.array([0.0, 1.0]), np.zeros((2, 3)), R, np.array([0.25]))[0]
    assert np.allclose(mid.R, cv2.Rodrigues(np.array([0.0, 0.0, np.pi / 8]))[0])


def test_build_matches_the_truth(built, scans):
    out, results = built
    assert [r.status for r in results] == ["ok"], results[0].reason
    acc = compare_to_truth(out / "train/s00000", scans / "gt/scans/s00000")
    assert acc["frames"] >= 14
    assert acc["rotation_median_deg"] < 0.5
    assert acc["centre_median_rel"] < 0.02  # metric scale from the drifting device track
    assert acc["overlap_correlation"] > 0.9


def test_built_scene_reads_as_mapfree(built):
    out, _ = built
    scene = Dataset(out).scene("train", "s00000")
    assert {f.seq for f in scene.frames.values()} == {"seq0", "seq1"}
    first = scene.poses.pose(0)
    assert np.allclose(first.R, np.eye(3), atol=1e-6) and np.allclose(first.t, 0, atol=1e-6)
    assert scene.device_poses is not None and len(scene.device_poses) == len(scene.frames)
    assert all(f.has_depth("sensor") for f in scene.frames.values())
    ov = read_overlaps(out / "train/s00000/overlaps.npz")
    assert len(ov) > 0 and (ov.idxs[:, 0] != ov.idxs[:, 2]).any() and (ov.overlaps <= 1).all()
    report = json.loads((out / "train/s00000/build_report.json").read_text())
    assert report["scale"]["source"] == "device" and report["reprojection_error_px"] < 2
    assert report["overlap_points"] == "depth"  # every frame came with sensor depth
    assert (out / "train/s00000/build_report.png").stat().st_size > 1000


def test_correspondences_follow_the_true_geometry(built, scans):
    """Correspondences come from the built poses; the true poses must map them onto each other too."""
    out, _ = built
    corr = read_correspondences(out / "train/s00000/correspondences.npz")
    assert corr
    truth = {}
    for k in (0, 1):
        table = read_poses(scans / f"gt/scans/s00000/scan{k}/poses.txt")
        truth.update({(k, i): table.pose(i) for i in range(len(table))})
    from mapfree.data import read_depth, read_intrinsics

    intr = read_intrinsics(out / "train/s00000/intrinsics.txt")
    errs = []
    for (sa, fa, sb, fb), (k0, k1) in list(corr.items())[:5]:
        na, nb = f"seq{sa}/frame_{fa:05d}.jpg", f"seq{sb}/frame_{fb:05d}.jpg"
        d = read_depth(out / "train/s00000" / na.replace(".jpg", ".sensor.png"))
        uv = k0.astype(np.float64)
        X = backproject(uv, d[uv[:, 1].astype(int), uv[:, 0].astype(int)], intr[na].K)
        rel: Pose = truth[(sb, fb)] @ truth[(sa, fa)].inverse()
        errs.append(np.linalg.norm(project(rel.transform(X), intr[nb].K) - k1, axis=1))
    assert np.median(np.concatenate(errs)) < 3.0  # pixels


def test_resume_and_clear_failures(built, scans, tmp_path):
    """A built place is skipped; a place whose second scan shows nothing of the first fails on its own."""
    out, _ = built
    report = out / "train/s00000/build_report.json"
    before = report.stat().st_mtime_ns
    root = tmp_path / "scans"
    shutil.copytree(scans / "scans/s00000", root / "s00000", symlinks=True)
    bad = root / "s00001"
    shutil.copytree(scans / "scans/s00000/scan0", bad / "scan0")
    (bad / "scan1").mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):  # another "place": smooth noise nothing in scan0 resembles
        img = cv2.GaussianBlur(rng.integers(0, 255, (320, 240, 3), dtype=np.uint8), (0, 0), 3)
        cv2.imwrite(str(bad / "scan1" / f"frame_{i:05d}.jpg"), img)
    results = build_all(root, out, BuildOptions(split="train"), progress=False)
    status = {r.scene: (r.status, r.reason) for r in results}
    assert status["s00000"][0] == "skipped" and report.stat().st_mtime_ns == before
    assert status["s00001"][0] == "failed"
    assert "scan1" in status["s00001"][1] and ("registered" in status["s00001"][1] or "overlap" in status["s00001"][1])
    assert not (out / "train/s00001").exists()  # no half-written scene
    assert json.loads((out / "train/build_summary.json").read_text())[1]["status"] == "failed"


def _images_only(scans: Path, root: Path, files: tuple[str, ...] = ()) -> None:
    """The test place's images (and ``files`` of each scan) alone under ``root/s00000``: no device track, no depth."""
    for k in (0, 1):
        src, dst = scans / f"scans/s00000/scan{k}", root / "s00000" / f"scan{k}"
        dst.mkdir(parents=True)
        for p in [*src.glob("frame_*.jpg"), *(src / f for f in files)]:
            (dst / p.name).symlink_to(p)


def test_no_metric_scale_is_a_clear_error(scans, tmp_path):
    _images_only(scans, tmp_path / "scans")
    # No device poses, no depth, no intrinsics: SfM guesses the focal length, the scale is unknown.
    res = build_all(
        tmp_path / "scans", tmp_path / "out", BuildOptions(split="train", report_plot=False), progress=False
    )
    assert res[0].status == "failed" and "no metric scale" in res[0].reason and "--allow-unscaled" in res[0].reason


@pytest.mark.parametrize(
    "corrupt, problem",
    [
        ("equal", "is equal to the previous one"),  # every timestamp the same (an export without a clock)
        ("backwards", "is before the previous one"),  # line 5 goes back in time
    ],
)
def test_device_track_without_increasing_times_fails_the_place_naming_file_and_line(scans, tmp_path, corrupt, problem):
    _images_only(scans, tmp_path / "scans", ("rgb.txt", "intrinsics.txt", "device_poses.txt"))
    track = tmp_path / "scans/s00000/scan1/device_poses.txt"
    lines = track.read_text().splitlines(keepends=True)
    track.unlink()  # a copy of the synthetic track, then corrupted
    assert len(lines) > 5 and all(not ln.startswith("#") for ln in lines)
    if corrupt == "equal":
        lines = [lines[0].split()[0] + " " + ln.split(maxsplit=1)[1] for ln in lines]
        line = 2
    else:
        lines[4] = lines[2].split()[0] + " " + lines[4].split(maxsplit=1)[1]
        line = 5
    track.write_text("".join(lines))
    res = build_all(
        tmp_path / "scans", tmp_path / "out", BuildOptions(split="train", report_plot=False), progress=False
    )
    assert res[0].status == "failed"
    assert f"{track}:{line}: timestamp" in res[0].reason and problem in res[0].reason, res[0].reason
    assert not (tmp_path / "out/train/s00000").exists()
    summary = json.loads((tmp_path / "out/train/build_summary.json").read_text())
    assert summary[0]["status"] == "failed" and f"device_poses.txt:{line}" in summary[0]["reason"]


@pytest.mark.slow
def test_ray_val_build_runs_and_evaluates(built, scans, tmp_path):
    """Ray tasks give the pool's poses; the val scene is a reference plus queries that mapfree run/evaluate score."""
    ray = pytest.importorskip("ray")
    out = tmp_path / "ray"
    try:
        rc = cli_main(["build", str(scans / "scans"), "--out", str(out), "--split", "val", "--ray", "local", "--quiet"])
    finally:
        ray.shutdown()
    assert rc == 0
    val = read_poses(out / "val/s00000/poses.txt")
    assert val.names[0] == "seq0/frame_00000.jpg" and all(n.startswith("seq1/") for n in val.names[1:])
    train = read_poses(built[0] / "train/s00000/poses.txt").as_dict()
    for i, n in enumerate(val.names[1:], 1):  # train's origin is the same reference frame
        assert np.allclose(val.pose(i).t, train[n].t, atol=1e-3)
    sub = tmp_path / "sub.zip"
    assert (
        cli_main(
            [
                "run",
                str(out),
                "--split",
                "val",
                "--method",
                "sift_emat_sensor",
                "-o",
                str(sub),
                "--all-frames",
                "--no-progress",
            ]
        )
        == 0
    )
    assert cli_main(["evaluate", str(sub), "--dataset", str(out), "--split", "val", "--json"]) == 0


REAL = Path("/work/shared/data/realmini-dev/val/s00000")


@pytest.mark.skipif(not REAL.is_dir(), reason="realmini-dev not available")
def test_exif_focal_length_of_a_real_photo(tmp_path):
    """A phone photo without intrinsics.txt: its EXIF 35 mm focal length gives the pinhole camera."""
    from PIL import Image

    from mapfree.data import read_intrinsics

    true = read_intrinsics(REAL / "intrinsics.txt")["seq0/frame_00000.jpg"]
    f35 = round(true.fx / max(true.width, true.height) * 36)  # what the phone would write, whole millimetres
    place = tmp_path / "statue"
    for k, src in enumerate(["seq0/frame_00000.jpg", "seq1/frame_00001.jpg"]):
        (place / f"scan{k}").mkdir(parents=True)
        with Image.open(REAL / src) as im:
            exif = Image.Exif()
            exif.get_ifd(0x8769)[0xA405] = f35  # Exif sub-IFD, FocalLengthIn35mmFilm
            im.save(place / f"scan{k}" / "frame_00000.jpg", exif=exif, quality=95)
            im.save(place / f"scan{k}" / "frame_00001.jpg", quality=95)  # no EXIF: focal unknown
    (place / "scan1" / "intrinsics.txt").write_text("frame_00000.jpg 500 501 270 180 540 360\n")
    scans = read_place(place).scans
    K = scans[0].frames[0].intrinsics
    assert (K.width, K.height) == (true.width, true.height)
    assert abs(K.fx - true.fx) / true.fx < 0.02 and K.fx == K.fy  # rounding to whole mm only
    assert (K.cx, K.cy) == ((true.width - 1) / 2, (true.height - 1) / 2)
    assert scans[0].frames[1].intrinsics is None
    assert scans[1].frames[0].intrinsics.fy == 501  # intrinsics.txt wins over EXIF


@pytest.mark.slow
@pytest.mark.timeout(240)  # a head that never answers must not hold CI
def test_ray_cluster_address(built, scans, tmp_path, monkeypatch):
    """A Ray head started apart from the build (as on a cluster): --ray HOST:PORT gives the pool's scene."""
    ray = pytest.importorskip("ray")
    import os
    import signal
    import socket
    import subprocess
    import sys
    import tempfile
    import time

    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")  # a throw-away loopback cluster: no token to hand around
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # Ray's socket paths must stay short

    host = "127.0.0.1"  # conftest keeps Ray on the loopback address, as tests must
    with socket.socket() as s:
        s.bind((host, 0))
        port = s.getsockname()[1]
    head = subprocess.Popen(
        [
            str(Path(sys.executable).parent / "ray"),
            "start",
            "--head",
            "--block",
            f"--port={port}",
            f"--node-ip-address={host}",
            "--num-cpus=1",
            "--object-store-memory=100000000",
            "--include-dashboard=false",
            f"--temp-dir={temp}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    out = tmp_path / "cluster"
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # wait for the head to accept connections
            with socket.socket() as s:
                if s.connect_ex((host, port)) == 0:
                    break
            time.sleep(0.5)
        else:
            pytest.fail("the Ray head did not start")
        results = build_all(
            scans / "scans",
            out,
            BuildOptions(split="train", report_plot=False),
            ray_address=f"{host}:{port}",
            progress=False,
        )
        assert ray.is_initialized() and ray.get_runtime_context().gcs_address.endswith(f":{port}")
    finally:
        ray.shutdown()
        os.killpg(head.pid, signal.SIGTERM)  # the head and the processes it started, nothing else
        with contextlib.suppress(subprocess.TimeoutExpired):
            head.wait(5)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(head.pid, signal.SIGKILL)  # stragglers of the same process group
        head.wait(10)
        shutil.rmtree(temp, ignore_errors=True)
    assert [r.status for r in results] == ["ok"], results[0].reason
    pool = read_poses(built[0] / "train/s00000/poses.txt").as_dict()
    mine = read_poses(out / "train/s00000/poses.txt").as_dict()
    assert mine.keys() == pool.keys()
    assert all(np.allclose(mine[n].t, pool[n].t, atol=1e-3) for n in pool)


def test_own_matcher_written_into_colmap_database(scans, tmp_path):
    """--matcher sift: our registry's keypoints and matches go into COLMAP's database and map as accurately."""
    import pycolmap

    from mapfree.matching import create
    from mapfree.scenebuild import SfmOptions

    opts = BuildOptions(split="train", report_plot=False, keep_work=True, sfm=SfmOptions(matcher="sift"))
    res = build_all(scans / "scans", tmp_path, opts, progress=False)
    assert [r.status for r in res] == ["ok"], res[0].reason
    acc = compare_to_truth(tmp_path / "train/s00000", scans / "gt/scans/s00000")
    assert acc["frames"] >= 14 and acc["rotation_median_deg"] < 1.0 and acc["centre_median_rel"] < 0.02
    assert acc["overlap_correlation"] > 0.9
    first = scans / "scans/s00000/scan0/frame_00000.jpg"
    ours = create("sift").extract(cv2.cvtColor(cv2.imread(str(first)), cv2.COLOR_BGR2RGB))
    with pycolmap.Database.open(tmp_path / "train/.build/s00000/colmap/database.db") as db:
        image = db.read_image_with_name("seq0/frame_00000.jpg")
        assert np.allclose(db.read_keypoints(image.image_id)[:, :2], ours.kpts, atol=1e-3)
        assert db.num_verified_image_pairs() > 20


def test_unknown_matcher_is_a_clear_error(scans, tmp_path, capsys):
    assert cli_main(["build", str(scans / "scans"), "--out", str(tmp_path), "--matcher", "nope", "--quiet"]) == 1
    assert "unknown --matcher 'nope'" in capsys.readouterr().err


def test_overlaps_from_sfm_tracks_without_depth(scans, tmp_path):
    """Frames without depth: overlaps come from the SfM tracks (the paper's recipe); forcing depth is an error."""
    from mapfree.scenebuild.place import BuildError, _overlaps

    _images_only(scans, tmp_path / "scans", ("intrinsics.txt",))
    res = build_all(
        tmp_path / "scans", tmp_path / "out", BuildOptions(report_plot=False, allow_unscaled=True), progress=False
    )
    assert res[0].status == "ok", res[0].reason
    assert res[0].report["overlap_points"] == "sfm" and res[0].report["scale"]["source"] == "none"
    ov = read_overlaps(tmp_path / "out/train/s00000/overlaps.npz")
    assert len(ov) > 0 and (ov.overlaps > 0).all() and (ov.overlaps <= 1).all()
    with pytest.raises(BuildError, match="needs a depth map"):
        _overlaps(None, ["seq0/frame_00000.jpg"], [], [], tmp_path, np.zeros(1), np.zeros(1), "depth")


def test_colmap_info_log_stays_off_the_console(scans, tmp_path, capfd):
    """COLMAP's INFO lines (about 180 for one small place) drowned the progress bar and --quiet; its
    warnings and errors still show."""
    assert cli_main(["build", str(scans / "scans"), "--out", str(tmp_path / "out"), "--split", "val", "--quiet"]) == 0
    err = capfd.readouterr().err
    assert not [ln for ln in err.splitlines() if ln.startswith("I20")], err[:500]

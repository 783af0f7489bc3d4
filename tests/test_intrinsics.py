"""Intrinsics of photos nobody calibrated: given, else EXIF, else the method's estimate, else the default camera.

Phone-style JPEGs are made here from real photos (realmini-dev, whose intrinsics are known): the pixels are
turned to a sensor's stored grid, the EXIF orientation that turns them back is written with the focal tags
(35 mm-equivalent, or focal length with the sensor's pixel density), sometimes at half size, and the resolved
intrinsics are compared with the known ones.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from cli_support import (
    FOCAL_35MM,
    FOCAL_LENGTH,
    FOCAL_PLANE_UNIT,
    FOCAL_PLANE_X_RES,
    PIXEL_X_DIM,
    phone_jpeg,
    stored_grid,
)
from mapfree.cli import main
from mapfree.data import read_image, read_intrinsics
from mapfree.data.intrinsics import (
    check_principal_point,
    default_fov_deg,
    exif_intrinsics,
    focal_from_35mm,
)
from mapfree.geometry import Intrinsics, backproject_depth, focal_from_pointmap, rotation_angle_deg
from mapfree.relocalize import photo_view

F35 = 33  # the realmini-dev camera: fx = 495.57 px on a 540 px long side = a 33.04 mm-equivalent lens


@pytest.fixture(scope="module")
def known(realmini):
    """The reference photo of realmini-dev s00000 (upright) and its calibrated intrinsics."""
    scene = realmini / "val" / "s00000"
    return read_image(scene / "seq0/frame_00000.jpg"), read_intrinsics(scene / "intrinsics.txt")["seq0/frame_00000.jpg"]


def test_the_35mm_convention_is_the_long_side_of_a_full_frame():
    assert focal_from_35mm(36, 4032, 3024) == 4032  # 36 mm on a 36 mm-wide frame: f = the long side
    assert focal_from_35mm(26, 3024, 4032) == pytest.approx(26 / 36 * 4032)  # portrait: the same long side
    assert default_fov_deg() == pytest.approx(64.0, abs=0.05)


@pytest.mark.parametrize("orientation", [1, 3, 6, 8])
@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_exif_35mm_focal_of_a_turned_resized_photo_matches_the_calibration(tmp_path, known, orientation, scale):
    upright, K = known
    path = tmp_path / "phone.jpg"
    phone_jpeg(path, upright, orientation, {FOCAL_35MM: F35}, scale)
    v = photo_view(path)
    H, W = round(K.height * scale), round(K.width * scale)
    assert v.image.shape[:2] == (H, W)  # upright, as every reader of ours returns it
    assert v.intrinsics_source == "exif" and v.intrinsics_detail == "FocalLengthIn35mmFilm 33 mm"
    k = v.intrinsics
    assert (k.width, k.height) == (W, H)
    assert k.fx == k.fy == pytest.approx(F35 / 36 * max(W, H))
    assert k.fx == pytest.approx(K.fx * scale, rel=2e-3)  # the calibration, up to EXIF's whole millimetres
    assert (k.cx, k.cy) == ((W - 1) / 2, (H - 1) / 2)
    assert exif_intrinsics(path) == k  # what mapfree build reads from a scan: the same convention


@pytest.mark.parametrize("orientation", [1, 6])
@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_exif_focal_length_with_the_sensor_density(tmp_path, known, orientation, scale):
    """``FocalLength`` (mm) x ``FocalPlaneXResolution`` (pixels per cm here) at the captured width
    (``PixelXDimension``); a photo resized afterwards keeps the tags of its capture."""
    upright, K = known
    stored_w = stored_grid(upright, orientation).shape[1]
    f_mm = 4.25
    tags = {FOCAL_LENGTH: f_mm, FOCAL_PLANE_X_RES: K.fx / f_mm * 10, FOCAL_PLANE_UNIT: 3, PIXEL_X_DIM: stored_w}
    path = tmp_path / "phone.jpg"
    phone_jpeg(path, upright, orientation, tags, scale)
    v = photo_view(path)
    assert v.intrinsics_source == "exif" and v.intrinsics_detail.startswith("FocalLength 4.25 mm")
    assert v.intrinsics.fx == v.intrinsics.fy == pytest.approx(K.fx * scale, rel=5e-3)  # the resize's rounding
    assert (v.intrinsics.width, v.intrinsics.height) == (round(K.width * scale), round(K.height * scale))


def test_no_tags_give_the_default_camera_and_given_intrinsics_win(tmp_path, known):
    upright, K = known
    path = tmp_path / "plain.jpg"
    phone_jpeg(path, upright, 6, {})
    v = photo_view(path)
    assert v.intrinsics_source == "default" and "64° across the long side" in v.intrinsics_detail
    assert v.intrinsics.fx == pytest.approx(0.8 * 540) and (v.intrinsics.width, v.intrinsics.height) == (540, 360)
    phone_jpeg(path, upright, 1, {FOCAL_35MM: 1})  # a junk tag (a 1 mm-equivalent lens): skipped
    assert photo_view(path).intrinsics_source == "default"
    phone_jpeg(
        path, upright, 1, {FOCAL_35MM: 1, FOCAL_LENGTH: 4.25, FOCAL_PLANE_X_RES: K.fx / 4.25, FOCAL_PLANE_UNIT: 4}
    )
    assert photo_view(path).intrinsics.fx == pytest.approx(K.fx)  # the next tags then
    tagged = tmp_path / "tagged.jpg"
    phone_jpeg(tagged, upright, 1, {FOCAL_35MM: 20})
    given = photo_view(tagged, K)
    assert given.intrinsics_source == "given" and given.intrinsics == K
    assert given.resolved.to_dict()["source"] == "given"


def test_a_principal_point_far_outside_the_image_is_refused(tmp_path, known):
    upright, K = known
    check_principal_point(-0.4 * 540, 1.4 * 360, 540, 360, "--K-ref")  # off-centre, but a possible camera
    with pytest.raises(ValueError, match=r"^--K-ref: principal point cx = 5000 is far outside the 540x360 image"):
        check_principal_point(5000, 180, 540, 360, "--K-ref")
    path = tmp_path / "a.jpg"
    phone_jpeg(path, upright, 1, {})
    with pytest.raises(ValueError, match="principal point cy = -400"):
        photo_view(path, (500, 500, 270, -400), what="fy")


def test_the_focal_that_explains_a_pointmap():
    """DUSt3R's estimate (Weiszfeld, centred principal point) recovers the focal of a back-projected depth map,
    also with a few wild points (the re-weighting is robust to them)."""
    K = Intrinsics(412.0, 412.0, 159.5, 119.5, 320, 240)
    rng = np.random.default_rng(0)
    depth = rng.uniform(1.0, 5.0, (240, 320))
    pts = backproject_depth(depth, K.K).reshape(240, 320, 3)
    assert focal_from_pointmap(pts) == pytest.approx(412.0, rel=1e-9)
    pts = pts.copy()
    pts.reshape(-1, 3)[rng.choice(pts.size // 3, 200, replace=False)] *= np.array([3.0, -2.0, 1.0])
    assert focal_from_pointmap(pts) == pytest.approx(412.0, rel=1e-3)
    assert np.isnan(focal_from_pointmap(np.zeros((4, 4, 3))))


def test_the_network_focal_is_brought_to_the_original_pixels():
    """A pointmap at the network's input (resized, centre-cropped) gives the focal of the original photo."""
    import torch

    from mapfree.mast3r.preprocess import Prepared, crop_box, resized_size
    from mapfree.matching.mast3r import focal_at_original

    w0, h0, f0 = 1080, 720, 860.0
    size = resized_size(w0, h0, 512)
    box = crop_box(*size)
    prep = Prepared(torch.zeros(1, 3, box[3] - box[1], box[2] - box[0]), (w0, h0), size, box)
    s = size[0] / w0
    h, w = prep.true_shape
    Kn = Intrinsics(f0 * s, f0 * s, (w - 1) / 2, (h - 1) / 2, w, h)
    pts = backproject_depth(np.full((h, w), 2.0), Kn.K).reshape(h, w, 3)
    assert focal_at_original(pts, prep) == pytest.approx(f0, rel=1e-3)  # 341 rows for 720 x 512 / 1080


def _pose(out: dict) -> tuple[np.ndarray, np.ndarray]:
    return np.array(out["R"]), np.array(out["t"])


def test_relocalize_two_turned_phone_photos_from_their_exif(tmp_path, realmini, capsys):
    """Two phone-style photos (stored sideways, EXIF orientation and 35 mm focal, the reference's depth map for
    its stored grid) give the pose the calibrated pair gives; the JSON names the source per image. The same
    photos without tags run on the default camera, with the warning."""
    scene = realmini / "val" / "s00000"
    ref, query = scene / "seq0/frame_00000.jpg", scene / "seq1/frame_00010.jpg"
    intr = read_intrinsics(scene / "intrinsics.txt")
    depth = np.asarray(Image.open(scene / "seq0/frame_00000.sensor.png"))
    assert main(["relocalize", str(ref), str(query), "--method", "sift_pnp_sensor"]) == 0
    truth = json.loads(capsys.readouterr().out)  # the scene's intrinsics.txt: given
    assert truth["intrinsics"]["reference"]["source"] == "given"

    for name, orientation, tags in (("a.jpg", 6, {FOCAL_35MM: F35}), ("b.jpg", 8, {FOCAL_35MM: F35})):
        phone_jpeg(tmp_path / name, read_image(ref if name == "a.jpg" else query), orientation, tags)
    Image.fromarray(stored_grid(depth, 6)).save(tmp_path / "a_depth.png")  # the phone's map: its stored grid
    args = ["relocalize", str(tmp_path / "a.jpg"), str(tmp_path / "b.jpg"), "--method", "sift_pnp_sensor"]
    assert main([*args, "--depth-ref", str(tmp_path / "a_depth.png")]) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert "warning" not in captured.err
    for side, (key, _o) in {"reference": ("seq0/frame_00000.jpg", 6), "query": ("seq1/frame_00010.jpg", 8)}.items():
        got = out["intrinsics"][side]
        assert got["source"] == "exif" and (got["width"], got["height"]) == (540, 360)
        assert got["fx"] == pytest.approx(intr[key].fx, rel=2e-3)
    R0, t0 = _pose(truth)
    R1, t1 = _pose(out)
    assert rotation_angle_deg(R0, R1) < 1.0  # the principal point moved 10 px to the centre, the focal 0.1 %
    assert np.linalg.norm(t1 - t0) < 0.05 * np.linalg.norm(t0)

    for name in ("a.jpg", "b.jpg"):
        phone_jpeg(tmp_path / name, read_image(tmp_path / name), 1, {})  # upright, no tags
    assert main([*args, "--depth-ref", str(tmp_path / "a_depth.png")]) == 1  # the map of the turned photo
    assert "another aspect ratio" in capsys.readouterr().err
    Image.fromarray(depth).save(tmp_path / "a_depth.png")
    rc = main([*args, "--depth-ref", str(tmp_path / "a_depth.png")])
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert rc in (0, 3) and out["intrinsics"]["query"]["source"] == "default"
    assert out["intrinsics"]["query"]["fx"] == pytest.approx(0.8 * 540)
    warnings = [ln for ln in captured.err.splitlines() if "warning" in ln]
    assert len(warnings) == 2 and all("the metric scale of the pose rests on it" in ln for ln in warnings)


def test_a_malformed_K_is_reported_before_any_file_problem(capsys):
    assert main(["relocalize", "nosuch.jpg", "nosuch2.jpg", "--method", "nope", "--K-query", "1,2,x,4"]) == 1
    assert capsys.readouterr().err.strip() == (
        "mapfree relocalize: error: --K-query: expected 4 comma-separated numbers, got '1,2,x,4'"
    )

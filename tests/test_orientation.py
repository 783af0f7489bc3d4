"""EXIF orientation: pixels turned upright with their intrinsics (half-pixel convention), on synthetic projections
and on a real photo re-saved with an orientation tag."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from mapfree.data import Dataset, FormatError, read_image
from mapfree.data.orientation import (
    OrientationError,
    camera_rotation,
    check_orientation,
    exif_orientation,
    fit_intrinsics,
    orient_intrinsics,
    orient_pixels,
)
from mapfree.geometry import Intrinsics, rotation_angle_deg
from mapfree.relocalize import Relocalizer

K0 = Intrinsics(495.6, 480.2, 251.3, 170.9, 540, 360)  # deliberately off-centre and fx != fy


def _save(path, rgb: np.ndarray, orientation: int, **kw) -> None:
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(rgb).save(path, exif=exif, **kw)


@pytest.mark.parametrize("o", [1, 3, 6, 8])
def test_a_projected_point_lands_on_the_turned_pixel_with_the_turned_K(o):
    rng = np.random.default_rng(o)
    X = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 5, 50)]  # points in the stored camera's frame
    uv = (K0.K @ X.T).T
    uv = uv[:, :2] / uv[:, 2:]
    # Mark the nearest pixel of each projection in the stored grid, turn the grid, find the marks again.
    grid = np.full((K0.height, K0.width), -1, np.int64)
    px = np.rint(uv).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < K0.width) & (px[:, 1] >= 0) & (px[:, 1] < K0.height)
    grid[px[inside, 1], px[inside, 0]] = np.flatnonzero(inside)
    turned = orient_pixels(grid, o)
    K1 = orient_intrinsics(K0, o)
    assert turned.shape == (K1.height, K1.width)
    Xr = (camera_rotation(o) @ X.T).T  # the same points in the upright camera's frame
    uv1 = (K1.K @ Xr.T).T
    uv1 = uv1[:, :2] / uv1[:, 2:]
    marked = np.unique(turned[turned >= 0])
    assert len(marked) > 30
    for i in marked:
        v, u = np.argwhere(turned == i)[0]
        # The turned pixel is where the stored pixel's centre went; the turned K projects the point there, up to
        # the rounding to that pixel (half a pixel each way), exactly as on the stored grid.
        assert np.allclose(uv1[i] - (u, v), np.array(_turn_offset(uv[i] - px[i], o)), atol=1e-9)


def _turn_offset(d: np.ndarray, o: int) -> tuple[float, float]:
    """A sub-pixel offset (du, dv) from a pixel centre, as seen after turning the grid."""
    du, dv = d
    return {1: (du, dv), 3: (-du, -dv), 6: (-dv, du), 8: (dv, -du)}[o]


def test_turning_back_and_forth_is_the_identity_and_mirrors_are_refused():
    assert orient_intrinsics(orient_intrinsics(K0, 6), 8) == K0
    assert orient_intrinsics(orient_intrinsics(K0, 3), 3) == K0
    for o in (2, 4, 5, 7):
        with pytest.raises(OrientationError, match="mirrored"):
            check_orientation(o, "photo.jpg")
    with pytest.raises(OrientationError, match="invalid EXIF orientation 9"):
        check_orientation(9)
    # Intrinsics sized like the stored grid are turned, sized like the upright photo kept, anything else refused.
    assert fit_intrinsics(K0, 360, 540, 6) == orient_intrinsics(K0, 6)
    up = orient_intrinsics(K0, 6)
    assert fit_intrinsics(up, 360, 540, 6) is up
    with pytest.raises(ValueError, match="intrinsics say 100x100"):
        fit_intrinsics(Intrinsics(1, 1, 1, 1, 100, 100), 360, 540, 6, "q.jpg")


def test_read_image_turns_tagged_photos_upright_and_refuses_mirrored_ones(tmp_path):
    rgb = np.zeros((8, 12, 3), np.uint8)  # at least 8 pixels a side (read_image refuses less)
    rgb[0, 0] = (255, 0, 0)  # a red top-left corner
    for o in (1, 3, 6, 8):
        _save(tmp_path / f"o{o}.png", orient_pixels(rgb, {1: 1, 3: 3, 6: 8, 8: 6}[o]), o)  # stored turned back
        assert exif_orientation(tmp_path / f"o{o}.png") == o
        assert np.array_equal(read_image(tmp_path / f"o{o}.png"), rgb), o
    _save(tmp_path / "mirror.png", rgb, 2)
    with pytest.raises(FormatError, match=r"mirror\.png.*mirrored"):
        read_image(tmp_path / "mirror.png")


@pytest.fixture(scope="module")
def scene(realmini):
    return Dataset(realmini).scene("val", "s00000")


@pytest.mark.parametrize("o,fmt", [(6, "png"), (8, "jpg"), (3, "png")])
def test_a_tagged_turned_photo_gives_the_pose_of_the_original(scene, tmp_path, o, fmt):
    """The query re-saved turned the other way with a tag that turns it back (as a phone stores it), with its
    intrinsics and depth map given for the stored grid: the pose equals the original's."""
    loc = Relocalizer("sift", "files:sensor", "essential")
    ref, q = scene.reference, scene.frame("seq1/frame_00010.jpg")
    ref_view = (ref.image_path, ref.intrinsics, ref.depth("sensor"))
    plain = loc.relocalize(ref_view, (q.image_path, q.intrinsics, q.depth("sensor")))
    undo = {3: 3, 6: 8, 8: 6}[o]  # stores the grid so that orientation o shows the original
    path = tmp_path / f"query.{fmt}"
    _save(path, orient_pixels(q.image(), undo), o, **({"quality": 98} if fmt == "jpg" else {}))
    tagged = loc.relocalize(
        ref_view, (path, orient_intrinsics(q.intrinsics, undo), orient_pixels(q.depth("sensor"), undo))
    )
    assert plain.ok and tagged.ok, (plain.reason, tagged.reason)
    # lossless: the very same pixels; JPEG re-encoding noise moves RANSAC a little (the pose is 0.2 m away)
    tol_m, tol_deg = (1e-6, 1e-4) if fmt == "png" else (0.06, 1.0)
    assert np.linalg.norm(tagged.pose.center - plain.pose.center) < tol_m
    assert rotation_angle_deg(tagged.pose.R, plain.pose.R) < tol_deg
    assert np.linalg.norm(plain.pose.center - q.pose.center) < 0.25


@pytest.mark.slow
def test_mapfree_relocalize_reads_a_sideways_phone_photo(scene, tmp_path):
    """The command line with a query stored sideways (orientation 6) and intrinsics.txt and a depth map for its
    stored grid: the same pose as the original photo (it used to be refused: the image did not match its
    intrinsics)."""
    import json
    import subprocess
    import sys

    from mapfree.data import write_depth, write_intrinsics

    ref, q = scene.reference, scene.frame("seq1/frame_00010.jpg")
    root = tmp_path / "s00000"
    for sub in ("seq0", "seq1"):
        (root / sub).mkdir(parents=True)
    (root / "seq0/frame_00000.jpg").write_bytes(ref.image_path.read_bytes())
    _save(root / "seq1/frame_00010.png", orient_pixels(q.image(), 8), 6)
    write_depth(root / "q.png", orient_pixels(q.depth("sensor"), 8))
    write_intrinsics(
        root / "intrinsics.txt",
        {"seq0/frame_00000.jpg": ref.intrinsics, "seq1/frame_00010.png": orient_intrinsics(q.intrinsics, 8)},
    )

    def pose(query, depth) -> np.ndarray:
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "mapfree",
                "relocalize",
                str(root / "seq0/frame_00000.jpg"),
                str(query),
                "--method",
                "sift_pnp_sensor",
                "--intrinsics",
                str(root / "intrinsics.txt") if query.parent.parent == root else str(scene.path / "intrinsics.txt"),
                "--depth-ref",
                str(ref.depth_path("sensor")),
                "--depth-query",
                str(depth),
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert r.returncode == 0, r.stderr[-2000:]
        out = json.loads(r.stdout)
        return np.array(out["R"]), np.array(out["t"])

    (R0, t0), (R1, t1) = pose(q.image_path, q.depth_path("sensor")), pose(root / "seq1/frame_00010.png", root / "q.png")
    assert rotation_angle_deg(R0, R1) < 1e-4 and np.linalg.norm(t1 - t0) < 1e-4  # the upright camera's pose


def test_build_reads_exif_intrinsics_for_the_upright_photo(tmp_path):
    """``mapfree build`` takes a phone photo's focal length from EXIF; for a sideways-stored photo the intrinsics
    are those of the upright photo every reader of ours decodes (they used to keep the stored grid's size)."""
    from mapfree.scenebuild.inputs import exif_intrinsics

    exif = Image.Exif()
    exif[0x0112] = 6
    exif.get_ifd(0x8769)[0xA405] = 26  # FocalLengthIn35mmFilm
    Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(tmp_path / "p.jpg", exif=exif)
    K = exif_intrinsics(tmp_path / "p.jpg")
    assert (K.width, K.height) == (30, 40) == read_image(tmp_path / "p.jpg").shape[1::-1]
    assert K.fx == K.fy == pytest.approx(26 / 36 * 40) and (K.cx, K.cy) == (14.5, 19.5)

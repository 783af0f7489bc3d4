"""Structure from motion of all scans of a place with pycolmap: SIFT, exhaustive matching, incremental mapping.

All images of all scans go into one COLMAP database, so the mapper reconstructs each scan and registers the
scans to each other in one step (cross-scan matches tie them together). The largest model is kept; images
it lacks are reported as unregistered. Known intrinsics are fixed (one PINHOLE camera per image: phones
refocus); unknown ones share one camera per scan whose focal length bundle adjustment refines.

``SfmOptions.matcher`` swaps COLMAP's SIFT for any matcher of ``mapfree.matching`` (e.g. ``xfeat``,
``aliked-lightglue``): its keypoints and every pair's matches are written into the COLMAP database, which
pycolmap then verifies geometrically and maps as usual.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry import Intrinsics, Pose

__all__ = ["SfmOptions", "SfmModel", "reconstruct"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SfmOptions:
    """Settings of the pycolmap reconstruction of a place.

    Attributes:
        max_features: SIFT features per image.
        max_image_size: Longer side for feature extraction, pixels.
        max_ratio: SIFT ratio test (stricter than COLMAP's 0.8, against repeated textures).
        min_inliers: Verified matches for an image pair to count.
        threads: Threads per place (places run in parallel).
        seed: RANSAC and mapper seed: the same inputs give the same model.
        matcher: ``colmap`` (pycolmap SIFT) or a ``mapfree.matching`` name whose matches are written into the
            database.
    """

    max_features: int = 4096  # SIFT features per image
    max_image_size: int = 1600  # longer side for feature extraction (pixels)
    max_ratio: float = 0.7  # SIFT ratio test; stricter than COLMAP's 0.8 against repeated textures
    min_inliers: int = 15  # verified matches for an image pair to count
    threads: int = 1  # per place; places run in parallel
    seed: int = 0  # RANSAC and mapper seed: the same inputs give the same model
    matcher: str = "colmap"  # "colmap" (pycolmap SIFT) or a mapfree.matching name written into the database


@dataclass
class SfmModel:
    """A reconstruction in SfM units: poses, intrinsics and which 3D points each image observes."""

    poses: dict[str, Pose]  # world-to-camera
    intrinsics: dict[str, Intrinsics]
    observations: dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (uv (n,2) pixels, point ids (n,))
    points: dict[int, np.ndarray] = field(default_factory=dict)  # point id -> xyz
    reprojection_error: float = float("nan")  # mean, pixels
    models: int = 1  # how many separate models the mapper produced

    def point_array(self, ids: np.ndarray) -> np.ndarray:
        return np.array([self.points[int(i)] for i in ids]).reshape(-1, 3)


def _pinhole(cam) -> Intrinsics:
    K = cam.calibration_matrix()
    return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(cam.width), int(cam.height))


def _indices(kpts: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Index into ``kpts`` of each matched pixel ``uv`` (matchers return coordinates); -1 where none is within
    half a pixel (dense matchers' off-grid points)."""
    from scipy.spatial import cKDTree

    if len(kpts) == 0 or len(uv) == 0:
        return np.full(len(uv), -1, np.int64)
    dist, idx = cKDTree(kpts).query(uv, distance_upper_bound=0.5)
    return np.where(np.isfinite(dist), idx, -1)


def _write_matches(db: Path, image_root: Path, names: list[str], pairs_file: Path, options: SfmOptions) -> None:
    """Keypoints and exhaustive pairwise matches of ``options.matcher`` into the database (COLMAP's ids)."""
    import pycolmap

    from ..data.io import read_image
    from ..matching import create

    matcher = create(options.matcher, device="cpu")
    pairs = []
    with pycolmap.Database.open(db) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        feats = {}
        for n in names:
            feats[n] = matcher.extract(read_image(image_root / n))  # upright, like every reader of ours
            d.write_keypoints(ids[n], np.asarray(feats[n].kpts, np.float32).reshape(-1, 2))
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                m = matcher.match(feats[a], feats[b])
                ia, ib = _indices(feats[a].kpts, m.kpts0), _indices(feats[b].kpts, m.kpts1)
                ok = (ia >= 0) & (ib >= 0)
                if ok.sum() >= options.min_inliers:
                    d.write_matches(ids[a], ids[b], np.stack([ia[ok], ib[ok]], 1).astype(np.uint32))
                    pairs.append(f"{a} {b}\n")
    pairs_file.write_text("".join(pairs))


def reconstruct(
    image_root: Path,
    names: list[str],
    intrinsics: dict[str, Intrinsics | None],
    work: Path,
    options: SfmOptions = SfmOptions(),
) -> SfmModel | None:
    """SfM of ``image_root/names`` (names like ``seq0/frame_00000.jpg``); None when nothing reconstructs.
    COLMAP logs warnings and errors only: its INFO lines (hundreds per place) would bury the progress."""
    import pycolmap

    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(pycolmap.logging.WARNING)
    try:
        return _reconstruct(image_root, names, intrinsics, work, options)
    finally:
        pycolmap.logging.minloglevel = level


def _reconstruct(
    image_root: Path, names: list[str], intrinsics: dict[str, Intrinsics | None], work: Path, options: SfmOptions
) -> SfmModel | None:
    import pycolmap

    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    db = work / "database.db"
    known = all(intrinsics.get(n) is not None for n in names)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    extract = pycolmap.FeatureExtractionOptions()
    extract.num_threads = options.threads
    extract.use_gpu = False
    extract.max_image_size = options.max_image_size
    extract.sift.max_num_features = options.max_features
    mode = pycolmap.CameraMode.PER_IMAGE if known else pycolmap.CameraMode.PER_FOLDER
    if options.matcher == "colmap":
        pycolmap.extract_features(
            db,
            image_root,
            image_names=names,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=extract,
            device=pycolmap.Device.cpu,
        )
    else:
        pycolmap.Database.open(db).close()  # import_images wants an existing database
        pycolmap.import_images(db, image_root, camera_mode=mode, image_names=names, options=reader)
    with pycolmap.Database.open(db) as d:  # our intrinsics replace COLMAP's guesses
        for im in d.read_all_images():
            K = intrinsics.get(im.name)
            if K is not None:
                cam = d.read_camera(im.camera_id)
                cam.params = [K.fx, K.fy, K.cx, K.cy]
                cam.has_prior_focal_length = True
                d.update_camera(cam)
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = options.threads
    match.use_gpu = False
    match.sift.max_ratio = options.max_ratio
    verify = pycolmap.TwoViewGeometryOptions()
    verify.min_num_inliers = options.min_inliers
    verify.ransac.random_seed = options.seed
    if options.matcher == "colmap":
        pycolmap.match_exhaustive(db, matching_options=match, verification_options=verify, device=pycolmap.Device.cpu)
    else:
        _write_matches(db, image_root, names, work / "pairs.txt", options)
        pycolmap.verify_matches(db, work / "pairs.txt", verify)
    mapper = pycolmap.IncrementalPipelineOptions()
    mapper.num_threads = options.threads
    mapper.random_seed = options.seed
    mapper.min_num_matches = options.min_inliers
    mapper.extract_colors = False
    mapper.ba_refine_focal_length = not known
    mapper.ba_refine_principal_point = False
    mapper.ba_refine_extra_params = False
    models = pycolmap.incremental_mapping(db, image_root, work / "sparse", mapper)
    if not models:
        return None
    rec = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    poses, intr, obs = {}, {}, {}
    for im in rec.images.values():
        if not im.has_pose:
            continue
        T = im.cam_from_world()
        poses[im.name] = Pose(T.rotation.matrix(), T.translation)
        intr[im.name] = _pinhole(rec.cameras[im.camera_id])
        pts = [(p.xy, p.point3D_id) for p in im.points2D if p.has_point3D()]
        uv = np.array([p[0] for p in pts], np.float64).reshape(-1, 2)
        obs[im.name] = (uv, np.array([p[1] for p in pts], np.int64))
    points = {int(pid): np.asarray(p.xyz, np.float64) for pid, p in rec.points3D.items()}
    return SfmModel(poses, intr, obs, points, float(rec.compute_mean_reprojection_error()), len(models))

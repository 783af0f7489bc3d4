"""Device (phone-tracking) poses for the multi-frame track: which frames it scores, drift, ``poses_device.txt``.

The multi-frame leaderboard scores the queries at linear index 9, 19, 29, … of a scene's query list
(``seq1`` frames sorted by number) and lets a method use each one's *burst*: that query and the 8 frames
before it, with the phone's tracking poses. ``poses_device.txt`` holds those poses re-based burst by burst
so that the burst's query is the identity. Frames outside every burst are not listed.

Real tracking drifts: ``DriftModel`` turns a true trajectory into a plausible VIO one (a few cm per metre of
travel, a heading error that grows slowly about gravity). Synthetic scenes are written with it; a scene with
ground truth but no ``poses_device.txt`` (our real sample data) gets its device poses *derived* the same way,
flagged ``derived=True``, since a simulation is not a phone's log.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import Pose
from .io import FormatError, iter_records, write_poses
from .scene import REFERENCE_NAME, Scene, frame_number

__all__ = [
    "BURST",
    "EVERY_MULTI",
    "DEVICE_FILE",
    "multiframe_bursts",
    "scene_bursts",
    "DriftModel",
    "simulate_device_trajectory",
    "rebase_bursts",
    "write_device_poses",
    "DevicePoses",
    "load_device_poses",
]

BURST = 9  # frames a multi-frame method may use: the query and the 8 before it
EVERY_MULTI = 10  # scored queries: linear index 9, 19, 29, …
DEVICE_FILE = "poses_device.txt"


def multiframe_bursts(names: Sequence[str], size: int = BURST, every: int = EVERY_MULTI) -> list[tuple[str, list[str]]]:
    """``(scored query, its burst oldest-first ending with the query)`` for every query the multi-frame track scores.

    Like the public multi-frame loader: the distinct ``seq1`` names sorted by frame number form the query
    list; positions ``size, size + every, …`` are scored, each with the ``size`` frames ending there (so
    position 0 and the positions between bursts are never used). Frame numbers may skip.

    Args:
        names: Frame names of a scene (other sequences are ignored).
        size: Frames per burst, the query included.
        every: Stride between scored queries.

    Returns:
        One ``(query, burst)`` per scored query.
    """
    queries = sorted({n for n in names if n.startswith("seq1/")}, key=lambda n: (frame_number(n), n))
    return [(queries[i], queries[i - size + 1 : i + 1]) for i in range(size, len(queries), every)]


def scene_bursts(scene: Scene) -> list[tuple[str, list[str]]]:
    """The multi-frame bursts of a scene (see ``multiframe_bursts``).

    Args:
        scene: The scene; its ``poses.txt`` names, else its ``intrinsics.txt`` names.

    Returns:
        One ``(query, burst)`` per scored query.
    """
    names = scene.poses.names if scene.poses is not None else list(scene.intrinsics)
    return multiframe_bursts(names)


@dataclass(frozen=True)
class DriftModel:
    """How a phone's visual-inertial tracking strays from the truth (per scan; distances in metres).

    Gravity is observed, so orientation drifts only in heading (about "up"): a per-scan bias in degrees per
    metre travelled plus a random walk. Tracked distances carry a per-scan scale error and a random walk.

    Attributes:
        scale_sigma: Std of the per-scan scale error of tracked distances (0.02: 2 cm per metre).
        noise_per_m: Std of the position random walk, metres per metre travelled.
        heading_rate_deg: Std of the per-scan heading bias, degrees per metre travelled.
        heading_walk_deg: Heading random walk, degrees per square-root metre.
        jitter_deg: Independent orientation noise of each frame, degrees.
        min_step: Metres of "travel" charged per frame even when standing still.
    """

    scale_sigma: float = 0.02  # std of the per-scan scale error of tracked distances (2 cm per metre)
    noise_per_m: float = 0.01  # std of the position random walk, metres per metre travelled
    heading_rate_deg: float = 0.5  # std of the per-scan heading bias, degrees per metre travelled
    heading_walk_deg: float = 0.2  # heading random walk, degrees per square-root metre
    jitter_deg: float = 0.05  # independent orientation noise of each frame
    min_step: float = 0.002  # metres of "travel" charged per frame even when standing still


def simulate_device_trajectory(
    poses: Sequence[Pose], up: np.ndarray, rng: np.random.Generator, model: DriftModel = DriftModel()
) -> list[Pose]:
    """World-to-camera device poses of a scan, in a device frame that coincides with the truth at frame 0.

    ``poses`` are the true world-to-camera poses in scan order, ``up`` the world's up direction (unit vector).
    """
    if not poses:
        return []
    from scipy.spatial.transform import Rotation  # only simulation needs it, not reading poses

    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    centers = np.stack([p.center for p in poses])
    scale = 1.0 + rng.normal(0.0, model.scale_sigma)
    bias = np.radians(rng.normal(0.0, model.heading_rate_deg))
    walk = np.radians(model.heading_walk_deg)
    heading = 0.0
    c_dev = centers[0].copy()
    out = [poses[0]]
    for k in range(1, len(poses)):
        step = centers[k] - centers[k - 1]
        dist = float(np.linalg.norm(step)) + model.min_step
        heading += bias * dist + rng.normal(0.0, walk * np.sqrt(dist))
        yaw = Rotation.from_rotvec(heading * up).as_matrix()
        c_dev = c_dev + yaw @ (scale * step + rng.normal(0.0, model.noise_per_m * dist, 3))
        jitter = Rotation.from_rotvec(rng.normal(0.0, np.radians(model.jitter_deg), 3)).as_matrix()
        R_c2w = yaw @ poses[k].R.T @ jitter
        out.append(Pose(R_c2w.T, -R_c2w.T @ c_dev))
    return out


def rebase_bursts(device: Mapping[str, Pose], bursts: Sequence[tuple[str, Sequence[str]]]) -> dict[str, Pose]:
    """Device poses re-based burst by burst so that each burst's query is the identity (``poses_device.txt``)."""
    out: dict[str, Pose] = {}
    for query, burst in bursts:
        to_query = device[query].inverse()
        for name in burst:
            out[name] = device[name] @ to_query
    return out


def write_device_poses(path: Path | str, rebased: Mapping[str, Pose]) -> None:
    """``poses_device.txt`` in frame-number order."""
    names = sorted(rebased, key=lambda n: (frame_number(n), n))
    write_poses(path, names, [rebased[n] for n in names])


@dataclass
class DevicePoses:
    """A scene's device poses (re-based per burst) and whether they were simulated from ground truth.

    Attributes:
        poses: Device pose by frame name, each burst re-based so that its query is the identity.
        derived: True when simulated from ground truth (``DriftModel``), not read from a file.
        source: The file read, or how the poses were derived.
    """

    poses: dict[str, Pose]
    derived: bool
    source: str  # the file read, or how they were derived

    def relative(self, frame: str, query: str) -> Pose | None:
        """Motion between two frames of a burst as the device tracked it.

        Args:
            frame: Name of a frame of the burst.
            query: Name of the burst's query.

        Returns:
            The transform from ``frame``'s camera to ``query``'s (``X_query = T · X_frame``), or None when
                either has no device pose.
        """
        a, b = self.poses.get(frame), self.poses.get(query)
        return None if a is None or b is None else b @ a.inverse()


def _derive(scene: Scene, model: DriftModel, seed: int) -> DevicePoses:
    """Device poses simulated from a scene's ground-truth query trajectory (up = the reference's -y)."""
    path = scene.path / DEVICE_FILE
    truth = {n: f.pose for n, f in scene.frames.items()}
    order = sorted((n for n in truth if n.startswith("seq1/")), key=lambda n: (frame_number(n), n))
    track = [p for n in order if (p := truth[n]) is not None]
    if not order or len(track) != len(order):
        raise FormatError(path, None, "missing, and the scene has no ground-truth query poses to derive it from")
    ref = truth.get(REFERENCE_NAME) or Pose.identity()
    up = ref.R.T @ np.array([0.0, -1.0, 0.0])  # the reference camera is held roughly upright
    rng = np.random.default_rng([seed, zlib.crc32(scene.name.encode())])
    device = dict(zip(order, simulate_device_trajectory(track, up, rng, model)))
    return DevicePoses(
        rebase_bursts(device, multiframe_bursts(order)),
        True,
        f"derived from {scene.path / 'poses.txt'} with simulated drift (seed {seed})",
    )


def load_device_poses(
    scene: Scene, derive: bool = True, model: DriftModel = DriftModel(), seed: int = 0
) -> DevicePoses:
    """The device poses of a scene for the multi-frame track.

    Args:
        scene: The scene.
        derive: Without ``poses_device.txt``, simulate the poses from the ground truth instead of failing.
        model: Drift of the simulation.
        seed: Seed of the simulation (with the scene name: the same poses on every run).

    Returns:
        The poses read from ``poses_device.txt``, or derived from ground truth (``derived`` True).

    Raises:
        FormatError: The file is malformed, or missing and cannot (or may not) be derived.
    """
    path = scene.path / DEVICE_FILE
    if path.is_file():
        poses: dict[str, Pose] = {}
        for lineno, name, v in iter_records(path, 7):
            if not np.linalg.norm(v[:4]) > 1e-8:
                raise FormatError(path, lineno, f"zero quaternion for {name}")
            poses[name] = Pose.from_qt(v[:4], v[4:])
        return DevicePoses(poses, False, str(path))
    if not derive:
        raise FormatError(path, None, "missing (the multi-frame track needs the device poses)")
    return _derive(scene, model, seed)

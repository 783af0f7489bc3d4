"""Verify a Map-free dataset folder: is a download (or a copy, or a build) complete and readable?

``check_dataset(ROOT)`` walks the splits and returns a ``CheckReport``: per split, the scenes found against the
release's (460 train, 65 val, 130 test; ``s00000``–``s00654``), the frames listed, the images checked, the depth
maps per suffix, and every problem found, each naming its file (and line). Images are checked cheaply by default
(the header read, its size compared with ``intrinsics.txt``, a JPEG's end marker present); ``deep=True`` decodes
every image and depth map.
"""

from __future__ import annotations

import os
import re
import zipfile
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..geometry import Intrinsics
from .io import FormatError, check_depth_size, pixel_problem, read_depth, read_image, read_intrinsics, read_poses
from .orientation import OrientationError, displayed_size, exif_orientation
from .overlaps import read_overlaps
from .scene import REFERENCE_NAME, SPLITS

__all__ = ["RELEASE", "Problem", "SplitReport", "CheckReport", "check_dataset", "check_scene"]

#: Scene numbers of the published release, per split.
RELEASE: dict[str, range] = {"train": range(0, 460), "val": range(460, 525), "test": range(525, 655)}

_SCENE_RE = re.compile(r"^s(\d{5})$")
_DEPTH_RE = re.compile(r"^(?P<stem>.+)\.(?P<suffix>[^.]+)\.png$")
_IMAGE_EXT = (".jpg", ".jpeg", ".png")


@dataclass
class Problem:
    """One thing wrong, named by its file (and 1-based line)."""

    path: str
    reason: str
    line: int | None = None

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.reason}" if self.line is not None else f"{self.path}: {self.reason}"


@dataclass
class SceneStats:
    """What one scene holds, and what is wrong with it."""

    frames: int = 0
    images_checked: int = 0
    unlisted_images: int = 0
    depth: dict[str, int] = field(default_factory=dict)
    problems: list[Problem] = field(default_factory=list)


@dataclass
class SplitReport:
    """One split: scenes found (and expected, for the whole release), frames, images, depth maps, problems."""

    split: str
    scenes: int = 0
    expected: int | None = None
    frames: int = 0
    images_checked: int = 0
    unlisted_images: int = 0
    depth: dict[str, int] = field(default_factory=dict)
    problems: list[Problem] = field(default_factory=list)

    def add(self, stats: SceneStats) -> None:
        self.scenes += 1
        self.frames += stats.frames
        self.images_checked += stats.images_checked
        self.unlisted_images += stats.unlisted_images
        for k, n in stats.depth.items():
            self.depth[k] = self.depth.get(k, 0) + n
        self.problems += stats.problems


@dataclass
class CheckReport:
    """The result of ``check_dataset``: ``ok`` when no split has a problem.

    Attributes:
        root: The folder checked.
        deep: Whether every image and depth map was decoded.
        subset: Whether any subset of the release's scenes was accepted.
        splits: One report per split checked.
        problems: Problems of the root itself (no split folder, not a dataset).
    """

    root: str
    deep: bool
    subset: bool
    splits: list[SplitReport] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)  # about the root itself (no split folder)

    @property
    def all_problems(self) -> list[Problem]:
        """Problems of the root, then of each split."""
        return self.problems + [p for s in self.splits for p in s.problems]

    @property
    def ok(self) -> bool:
        """True when nothing is wrong."""
        return not self.all_problems

    def to_dict(self) -> dict:
        """JSON-ready form (``mapfree check --json``): the fields, ``ok``, and each problem as one line."""
        d = asdict(self)
        d["ok"] = self.ok
        d["problems"] = [str(p) for p in self.problems]
        for s, sd in zip(self.splits, d["splits"]):
            sd["problems"] = [str(p) for p in s.problems]
        return d


def _image_header(path: Path) -> tuple[int, int]:
    """(width, height) of the photo as displayed (its EXIF orientation applied, as ``read_image`` does) from the
    file's header, without decoding; ValueError when it is not a readable image (or a mirrored one)."""
    import warnings

    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():  # Pillow's DecompressionBombWarning: the pixel budget below words it
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                w, h = im.size
                fmt = im.format
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as e:
        raise ValueError(f"not a readable image ({e.__class__.__name__})") from None
    if (problem := pixel_problem(w, h)) is not None:
        raise ValueError(problem)
    if fmt == "JPEG":
        with open(path, "rb") as f:  # a truncated download loses the end-of-image marker
            f.seek(max(0, path.stat().st_size - 64))
            if b"\xff\xd9" not in f.read():
                raise ValueError("truncated JPEG (no end-of-image marker)")
    try:
        return displayed_size(w, h, exif_orientation(path))
    except OrientationError as e:  # worded as the decoding reader words it
        raise ValueError(str(e).split(": ", 1)[1]) from None


def _depth_header(path: Path) -> tuple[int, int]:
    """(width, height) of a depth PNG from its header; ValueError unless it is a 16-bit single-channel PNG."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            mode, size, fmt = im.mode, im.size, im.format
    except (UnidentifiedImageError, OSError) as e:
        raise ValueError(f"not a readable PNG ({e.__class__.__name__})") from None
    if fmt != "PNG" or mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise ValueError(f"depth must be a single-channel 16-bit PNG, got {fmt} mode {mode}")
    return size


def _format_problem(e: FormatError) -> Problem:
    return Problem(e.path, e.reason, e.line)


def _is_identity(q: np.ndarray, t: np.ndarray) -> bool:
    return bool(np.allclose(np.abs(q), [1, 0, 0, 0], atol=1e-6) and np.allclose(t, 0, atol=1e-6))


def check_scene(path: os.PathLike | str, split: str, deep: bool = False) -> SceneStats:
    """Check one scene folder ``ROOT/SPLIT/sNNNNN``: text files, images, depth maps; never raises for bad data.

    Args:
        path: The scene folder.
        split: Its split: val and test scenes need the reference frame, train scenes ``overlaps.npz``.
        deep: Decode every image and depth map instead of reading headers.

    Returns:
        What the scene holds and every problem found, each naming its file (and line).
    """
    path = Path(path)
    st = SceneStats()
    intr = _check_tables(path, split, st)
    _check_frames(path, intr, deep, st)
    return st


def _check_tables(path: Path, split: str, st: SceneStats) -> dict[str, Intrinsics]:
    """The scene's text files and ``overlaps.npz``: readable, consistent, the reference frame where needed.

    Returns:
        The intrinsics by frame name (empty when ``intrinsics.txt`` is unreadable).
    """
    try:
        intr = read_intrinsics(path / "intrinsics.txt")
    except FormatError as e:
        st.problems.append(_format_problem(e))
        intr = {}
    try:
        poses = read_poses(path / "poses.txt")
    except FormatError as e:
        st.problems.append(_format_problem(e))
        poses = None
    st.frames = len(intr)

    if poses is not None:
        index = poses.index()
        lacking = [n for n in poses.names if n not in intr]
        if lacking and intr:
            st.problems.append(
                Problem(
                    str(path / "intrinsics.txt"),
                    f"no intrinsics for {len(lacking)} frame(s) of poses.txt, e.g. {lacking[0]}",
                )
            )
        if split == "val" and REFERENCE_NAME in index:
            i = index[REFERENCE_NAME]
            if not _is_identity(poses.q[i], poses.t[i]):
                st.problems.append(
                    Problem(
                        str(path / "poses.txt"), f"the reference {REFERENCE_NAME} must have the identity pose", i + 1
                    )
                )
    if split in ("val", "test") and intr and REFERENCE_NAME not in intr:
        st.problems.append(Problem(str(path / "intrinsics.txt"), f"no reference image {REFERENCE_NAME} listed"))

    if (path / "poses_device.txt").is_file():
        try:
            read_poses(path / "poses_device.txt")
        except FormatError as e:
            st.problems.append(_format_problem(e))
    if split == "train":
        try:
            ov = read_overlaps(path / "overlaps.npz")
            if len(ov.overlaps) and not (np.all(ov.overlaps >= 0) and np.all(ov.overlaps <= 1)):
                st.problems.append(Problem(str(path / "overlaps.npz"), "overlaps outside [0, 1]"))
        except FormatError as e:
            st.problems.append(_format_problem(e))
    return intr


def _check_frames(path: Path, intr: dict[str, Intrinsics], deep: bool, st: SceneStats) -> None:
    """Every listed frame present and readable, with the size its intrinsics give; then what is on disk beside
    the listed frames: unlisted images, and depth maps per suffix."""
    for name, K in intr.items():
        img = path / name
        if not img.is_file():
            st.problems.append(Problem(str(img), "listed in intrinsics.txt but missing"))
            continue
        st.images_checked += 1
        size = _measure(img, read_image, _image_header, deep, st)
        if size is None:
            continue
        w, h = size
        if (w, h) != (K.width, K.height):
            st.problems.append(Problem(str(img), f"image is {w}x{h} but intrinsics.txt says {K.width}x{K.height}"))

    listed = set(intr)
    for seq in sorted(p for p in path.iterdir() if p.is_dir() and p.name.startswith("seq")):
        for entry in os.scandir(seq):
            m = _DEPTH_RE.match(entry.name)
            if m:
                st.depth[m["suffix"]] = st.depth.get(m["suffix"], 0) + 1
                _check_depth(Path(entry.path), intr.get(f"{seq.name}/{m['stem']}.jpg"), deep, st)
            elif entry.name.lower().endswith(_IMAGE_EXT) and f"{seq.name}/{entry.name}" not in listed:
                st.unlisted_images += 1


def _measure(
    p: Path, decode: Callable[[Path], np.ndarray], header: Callable[[Path], tuple[int, int]], deep: bool, st: SceneStats
) -> tuple[int, int] | None:
    """(width, height) of an image file, from its header or (``deep``) by decoding it; None, with the problem
    recorded, when the file is empty or unreadable."""
    try:
        if p.stat().st_size == 0:
            raise ValueError("empty file")
        if deep:
            h, w = decode(p).shape[:2]
            return w, h
        return header(p)
    except FormatError as e:
        st.problems.append(Problem(str(p), e.reason))
    except Exception as e:  # noqa: BLE001 - any decoder failure is a finding, named with its file
        st.problems.append(Problem(str(p), str(e) or e.__class__.__name__))
    return None


def _check_depth(p: Path, K, deep: bool, st: SceneStats) -> None:
    """A depth map: a 16-bit PNG (header; ``deep``: decoded) of its image's aspect ratio."""
    size = _measure(p, read_depth, _depth_header, deep, st)
    if size is None:
        return
    w, h = size
    if K is not None:
        try:
            check_depth_size(p, (h, w), K.width, K.height)  # the readers' own rule
        except FormatError as e:
            st.problems.append(Problem(str(p), e.reason))


def _check_one(args: tuple[str, str, bool]) -> SceneStats:
    return check_scene(*args)


def not_a_dataset_folder(root: Path) -> str:
    """Why ``root`` is no dataset folder: it does not exist, or it is a file (a ZIP of the release, say)."""
    if not root.exists():
        return "no such folder"
    if zipfile.is_zipfile(root):
        return "a ZIP file, not a dataset folder: unzip it and check the folder it makes"
    return "a file, not a dataset folder"


def check_dataset(
    root: os.PathLike | str,
    splits: Sequence[str] | None = None,
    *,
    subset: bool = False,
    deep: bool = False,
    workers: int = 1,
    progress: Callable[[Iterable[SceneStats], int], Iterable[SceneStats]] | None = None,
) -> CheckReport:
    """Check that a dataset folder (a download, a copy, a build) is complete and readable (``mapfree check``).

    Args:
        root: The dataset folder.
        splits: The splits to check; default all three for the release, the ones present with ``subset``.
        subset: Accept any subset of ``sNNNNN`` scenes (a partial copy, synthetic or built data) instead of
            expecting the release's scenes.
        deep: Decode every image and depth map instead of reading headers.
        workers: Scenes checked in parallel processes.
        progress: Wraps the stream of finished scenes (e.g. a progress bar), given the number of scenes.

    Returns:
        Per split, the scenes, frames, images and depth maps found and every problem.

    Raises:
        ValueError: ``splits`` names an unknown split.
    """
    root = Path(root)
    report = CheckReport(str(root), deep, subset)
    if not root.is_dir():
        report.problems.append(Problem(str(root), not_a_dataset_folder(root)))
        return report
    unknown = [s for s in (splits or []) if s not in SPLITS]
    if unknown:
        raise ValueError(f"unknown split(s) {unknown}; the splits are {', '.join(SPLITS)}")
    present = [s for s in SPLITS if (root / s).is_dir()]
    wanted = list(splits) if splits else (present if subset else list(SPLITS))
    if not present:
        report.problems.append(Problem(str(root), "no train/, val/ or test/ folder: not a Map-free dataset root"))
        return report

    jobs: list[tuple[str, str, bool]] = []
    for split in wanted:
        rep = SplitReport(split, expected=None if subset else len(RELEASE[split]))
        report.splits.append(rep)
        jobs += _scene_jobs(root / split, rep, subset, deep)
    _run(report, jobs, workers, progress)
    return report


def _scene_jobs(d: Path, rep: SplitReport, subset: bool, deep: bool) -> list[tuple[str, str, bool]]:
    """The scenes of one split folder to check, with the problems of the folder itself recorded in ``rep``:
    missing, a folder that is no scene, (not ``subset``) a scene of the release missing or one not in it."""
    split = rep.split
    if not d.is_dir():
        rep.problems.append(Problem(str(d), "split folder missing"))
        return []
    names = sorted(p.name for p in d.iterdir() if p.is_dir())
    scenes = [n for n in names if _SCENE_RE.match(n)]
    for n in names:
        if n not in scenes and not n.startswith("."):
            rep.problems.append(Problem(str(d / n), "not a scene folder name (sNNNNN)"))
    if not subset:
        release = {f"s{i:05d}" for i in RELEASE[split]}
        missing = sorted(release.difference(scenes))
        if missing:
            shown = ", ".join(missing[:8]) + (f", … ({len(missing)} in all)" if len(missing) > 8 else "")
            rep.problems.append(
                Problem(str(d), f"{len(missing)} of the release's {len(release)} scenes missing: {shown}")
            )
        for n in sorted(set(scenes) - release):
            rep.problems.append(
                Problem(
                    str(d / n),
                    f"not a {split} scene of the release (s{RELEASE[split].start:05d}–s{RELEASE[split].stop - 1:05d})",
                )
            )
    return [(str(d / n), split, deep) for n in scenes]


def _run(
    report: CheckReport,
    jobs: list[tuple[str, str, bool]],
    workers: int,
    progress: Callable[[Iterable[SceneStats], int], Iterable[SceneStats]] | None,
) -> None:
    """Check the scenes (in ``workers`` processes), adding each to its split's report."""
    if workers > 1 and len(jobs) > 1:
        pool = ProcessPoolExecutor(workers)
        results: Iterable[SceneStats] = pool.map(_check_one, jobs, chunksize=4)
    else:
        pool = None
        results = map(_check_one, jobs)
    try:
        stream = progress(results, len(jobs)) if progress else results
        by_split = {r.split: r for r in report.splits}
        for job, stats in zip(jobs, stream):
            by_split[job[1]].add(stats)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)

"""The multi-frame track: relocalize every frame of a query's burst, move them to the query, fuse robustly.

Each of the 9 frames of a burst (the scored query and the 8 before it) is relocalized against the reference
on its own. The phone's tracking (``poses_device.txt``) carries each estimate to the scored query:
``T_query = (D_query · D_frame⁻¹) · T_frame``. The hypotheses are then fused:

1. consensus: every hypothesis proposes itself; the others agree with it when their rotation is within
   ``rotation_deg`` and their camera centre within ``translation_m`` (+ ``translation_rel`` of the distance
   to the reference, so far queries tolerate proportionally more); the proposal with the largest vote
   wins, each agreeing frame voting the square root of its confidence (confidence counts, but one very
   confident frame cannot outvote several that agree); RANSAC over at most 9 hypotheses, hence exhaustive;
2. the agreeing set is averaged (weighted chordal rotation mean, weighted centre) and re-selected around
   the average until stable;
3. the fused confidence is the agreeing confidence times the fraction of the burst that agrees, so a pose
   nine frames confirm outranks one a single frame proposes.

Frames without an estimate or a device pose are skipped; a burst with no hypothesis is "no estimate".
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ..benchmark import write_submission
from ..data import Dataset, DevicePoses, Scene, load_device_poses, scene_bursts
from ..data.io import naming
from ..estimate import Estimate
from ..geometry import Pose
from .journal import Failure, FrameRecord, Journal, failures_path, write_failures
from .preflight import pick_scenes
from .run import RunResult, run_split

__all__ = ["FusionOptions", "Hypothesis", "hypotheses", "fuse", "frames_path", "MultiRunResult", "run_multi"]


@dataclass(frozen=True)
class FusionOptions:
    """Consensus thresholds of the burst fusion."""

    rotation_deg: float = 10.0  # hypotheses this close in rotation …
    translation_m: float = 0.3  # … and this close in camera centre (metres) …
    translation_rel: float = 0.1  # … plus this fraction of their distance to the reference agree
    iterations: int = 3  # re-average and re-select around the average at most this often


@dataclass
class Hypothesis:
    """The scored query's world-to-camera pose implied by one frame of its burst."""

    frame: str
    pose: Pose
    confidence: float


def hypotheses(
    query: str, burst: Sequence[str], estimates: Mapping[str, tuple[Pose, float]], device: DevicePoses
) -> list[Hypothesis]:
    """Bring each burst frame's estimate (world-to-camera, confidence) to ``query`` through the device poses."""
    out = []
    for name in burst:
        if name not in estimates:
            continue
        pose, conf = estimates[name]
        if name == query:
            out.append(Hypothesis(name, pose, conf))
            continue
        to_query = device.relative(name, query)
        if to_query is not None:
            out.append(Hypothesis(name, to_query @ pose, conf))
    return out


def _agree(R: np.ndarray, C: np.ndarray, R0: np.ndarray, c0: np.ndarray, opts: FusionOptions) -> np.ndarray:
    """(n, m) whether hypothesis i agrees with candidate j (rotations R0[j], centres c0[j])."""
    cos = (np.einsum("iab,jab->ij", R, R0) - 1.0) / 2.0
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    dist = np.linalg.norm(C[:, None] - c0[None], axis=2)
    tol = opts.translation_m + opts.translation_rel * 0.5 * (
        np.linalg.norm(C, axis=1)[:, None] + np.linalg.norm(c0, axis=1)[None]
    )
    return (angle < opts.rotation_deg) & (dist < tol)


def _mean(R: np.ndarray, C: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.from_matrix(R).mean(weights=w).as_matrix(), (w[:, None] * C).sum(0) / w.sum()


def fuse(hyps: Sequence[Hypothesis], n_frames: int | None = None, options: FusionOptions = FusionOptions()) -> Estimate:
    """One pose for the scored query from its burst's hypotheses (robust, confidence-weighted; see module doc).

    ``n_frames``: the burst's size (frames without a hypothesis count against the agreement); default len(hyps).
    """
    hyps = [h for h in hyps if h.pose.is_finite()]
    n_frames = max(n_frames or len(hyps), len(hyps))
    if not hyps:
        return Estimate.failure("no frame of the burst has an estimate")
    R = np.stack([h.pose.R for h in hyps])
    C = np.stack([h.pose.center for h in hyps])
    conf = np.array([float(h.confidence) for h in hyps])
    conf = np.where(np.isfinite(conf) & (conf > 0), conf, 0.0)  # NaN or negative: no confidence
    top = conf.max()
    w = np.maximum(conf, 1e-3 * top) if top > 0 else np.ones(len(hyps))  # all-zero confidences: equal votes
    agree = _agree(R, C, R, C, options)
    votes = np.sqrt(w)  # sub-linear: several agreeing frames outweigh one very confident frame
    inl = agree[:, int(np.argmax(votes @ agree + 1e-9 * w))]
    for _ in range(options.iterations):
        R_m, c_m = _mean(R[inl], C[inl], w[inl])
        again = _agree(R, C, R_m[None], c_m[None], options)[:, 0]
        if not again.any() or np.array_equal(again, inl):
            break
        inl = again
    R_m, c_m = _mean(R[inl], C[inl], w[inl])
    k = int(inl.sum())
    fused_conf = float(w[inl].sum()) * k / n_frames
    pose = Pose(R_m, -R_m @ c_m)
    spread_deg = float(np.degrees(Rotation.from_matrix(R[inl] @ R_m.T).magnitude()).max())
    extras = {
        "support": k,
        "hypotheses": len(hyps),
        "frames": n_frames,
        "spread_deg": spread_deg,
        "spread_m": float(np.linalg.norm(C[inl] - c_m, axis=1).max()),
        "frames_used": [h.frame for h, used in zip(hyps, inl) if used],
    }
    return Estimate(pose, fused_conf, k, "", {}, extras)


# --------------------------------------------------------------------------- a whole split


def _beside(output: os.PathLike | str, suffix: str) -> Path:
    p = Path(output)
    return p.with_name(f"{p.stem}.{suffix}")


def frames_path(output: os.PathLike | str) -> Path:
    """``out/multi.zip`` -> ``out/multi.frames.zip``: the single-frame estimates of every burst frame."""
    return _beside(output, "frames.zip")


def fusion_path(output: os.PathLike | str) -> Path:
    """``out/multi.zip`` -> ``out/multi.fusion.jsonl``: per scored query, which frames agreed."""
    return _beside(output, "fusion.jsonl")


@dataclass
class MultiRunResult:
    """A multi-frame run: the fused submission, the per-frame run behind it, and where device poses came from."""

    submission: Path
    fusion: Path
    failures: Path
    frames: RunResult
    estimated: int = 0
    failed: int = 0
    derived_device_poses: list[str] = field(default_factory=list)  # scenes whose device poses were simulated

    def to_dict(self) -> dict[str, Any]:
        d = {k: (str(v) if isinstance(v, Path) else v) for k, v in self.__dict__.items() if k != "frames"}
        d["frames"] = self.frames.to_dict()
        return d


def _frame_estimates(recs: Sequence[FrameRecord], confidence: str | None) -> dict[str, dict[str, tuple[Pose, float]]]:
    """{scene: {frame: (world-to-camera pose, confidence)}} of the journal's successful frames."""
    out: dict[str, dict[str, tuple[Pose, float]]] = {}
    for r in recs:
        if r.ok:
            out.setdefault(r.scene, {})[r.frame] = (r.world_pose(), r.score(confidence))
    return out


#: Each scene's bursts (``[(scored query, burst frames)]``) and the device poses that carry them to the query.
_Plan = dict[str, tuple[list[tuple[str, list[str]]], DevicePoses]]


def _burst_plan(root: os.PathLike | str, split: str, scenes: Sequence[str] | None, derive: bool) -> _Plan:
    """The bursts of the split's (or the named) scenes, with their device poses (``derive``: from ground truth
    where a scene has none)."""
    scene_list = Dataset(root).scenes(split)
    if scenes:
        scene_list = pick_scenes(scene_list, scenes, split)  # an unknown name is refused, not ignored
    plan: _Plan = {}
    for s in scene_list:
        bursts = scene_bursts(s)
        plan[s.name] = (
            bursts,
            load_device_poses(s, derive=derive) if bursts else DevicePoses({}, False, "no bursts"),
        )
    return plan


def _fuse_split(
    plan: _Plan, estimates: Mapping[str, Mapping[str, tuple[Pose, float]]], options: FusionOptions
) -> tuple[dict[str, list], list[Failure], list[dict[str, Any]]]:
    """Each burst fused into its scored query: the submission's entries by scene, the failures, the fusion log."""
    by_scene: dict[str, list] = {name: [] for name in plan}
    failures, log = [], []
    for name, (bursts, device) in plan.items():
        for query, burst in bursts:
            fused = fuse(hypotheses(query, burst, estimates.get(name, {}), device), len(burst), options)
            entry = {
                "scene": name,
                "frame": query,
                "ok": fused.ok,
                "confidence": fused.confidence,
                "reason": fused.reason,
                **{k: v for k, v in fused.extras.items()},
            }
            log.append(entry)
            if fused.ok:
                by_scene[name].append((query, fused.pose, fused.confidence))
            else:
                failures.append(Failure(name, query, fused.reason))
    return by_scene, failures, log


def run_multi(
    root: os.PathLike | str,
    split: str,
    method: Any,
    output: os.PathLike | str,
    *,
    options: FusionOptions = FusionOptions(),
    derive_device_poses: bool = True,
    scenes: Sequence[str] | None = None,
    confidence: str | None = None,
    **run_kwargs: Any,
) -> MultiRunResult:
    """The multi-frame track of ``split``: relocalize every burst frame (``run_split``, resumable, journal
    beside ``frames_path(output)``), fuse each burst into its scored query, write the submission ``output``.

    Scenes without ``poses_device.txt`` get device poses derived from their ground truth when
    ``derive_device_poses`` (listed in the result); otherwise, or without ground truth, a ``FormatError``.
    ``all_frames`` is refused (``ValueError``): the frames run are the bursts, never every query.
    """
    if run_kwargs.pop("all_frames", False):
        raise ValueError(
            "all_frames does not apply to the multi-frame track (it runs the bursts of the scored queries)"
        )
    output = Path(output)
    plan = _burst_plan(root, split, scenes, derive_device_poses)

    def select(scene: Scene) -> list[str]:
        return [n for _, burst in plan[scene.name][0] for n in burst if n in scene.intrinsics]

    frames = run_split(
        root,
        split,
        method,
        frames_path(output),
        scenes=sorted(plan),
        confidence=confidence,
        select=select,
        **run_kwargs,
    )
    est = _frame_estimates(Journal.read(frames.journal).frames, confidence)
    by_scene, failures, log = _fuse_split(plan, est, options)
    write_submission(output, by_scene)
    write_failures(output, failures)
    with naming(fusion_path(output)):
        fusion_path(output).write_text("".join(json.dumps(e, allow_nan=False) + "\n" for e in log))
    derived = sorted(n for n, (_, d) in plan.items() if d.derived)
    return MultiRunResult(
        output,
        fusion_path(output),
        failures_path(output),
        frames,
        sum(len(v) for v in by_scene.values()),
        len(failures),
        derived,
    )

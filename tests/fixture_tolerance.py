"""Tolerances of the exactness tests against the public code's recorded outputs (shared/fixtures), one per kind of
output, and the error measures they bound.

A tolerance is set from the float32 spread of the same forward through the other CPU kernel paths a user's
machine may take (``ATEN_CPU_CAPABILITY=default|avx2|avx512``, one or two threads, the explicit softmax the
public code computes or PyTorch's fused attention), measured by ``bench/kernel_spread.py``: about 2.5 to 4 times
the largest error seen there. Where values pass through ``exp`` (MASt3R's points and confidences) a few values of a
map can move by 1e-4 between kernel paths, while a port error moves most of them: those kinds also bound the mean
error over the map, tightly. ``test_one_weight_off_fails_the_tolerances`` (in each fixture test module) checks the
other side: one weight of the network changed by 1 % fails, so no tolerance is wide enough to hide a port error.

With ``MAPFREE_FIXTURE_ERRORS=FILE`` set, every checked error is appended to FILE (one JSON line each) instead of
asserted, so that one run records every output: that is how ``bench/kernel_spread.py`` measures the spread through
the tests themselves, and judges it against these tolerances.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Tolerance:
    """The largest error allowed on any value, and (where set) on the mean over the array; what the error is."""

    max: float
    mean: float | None
    measure: str


# The spread measured on 2026-11-29 (2-core AMD EPYC, AVX2, no AVX-512) by bench/kernel_spread.py over the paths
# default|avx2 x 1|2 threads x fused|explicit attention, in the comments: the largest error of any path, and for
# the kinds with a mean bound the largest mean over one array. The fixtures were recorded on an AVX2 CPU with the
# explicit softmax: that path reproduces MASt3R's descriptors bit for bit. The full-size networks (slow tests) were
# measured on avx2 / 1 thread / fused (the CI path) and fall within the tiny models' spread.
TOLERANCES: dict[str, Tolerance] = {
    # MASt3R / DUSt3R: values pass through exp (points up to 1e5), so per point relative to the point's norm.
    "mast3r.pts3d": Tolerance(4e-4, 1.5e-5, "per point, relative to its norm"),  # 1.6e-4 / 5.5e-6
    "mast3r.conf": Tolerance(1e-4, 1.5e-5, "per value, relative"),  # 2.8e-5 / 5.5e-6
    "mast3r.desc": Tolerance(5e-6, 2e-6, "per descriptor, relative to its (unit) norm"),  # 1.6e-6 / 7.0e-7
    "mast3r.desc_conf": Tolerance(5e-6, 1e-6, "per value, relative"),  # 1.7e-6 / 3.8e-7
    # MicKey: keypoints, depths, scores and descriptors relative to the array's largest magnitude.
    "mickey.features": Tolerance(5e-6, None, "relative to the array's largest magnitude"),  # 1.5e-6
    "mickey.scores": Tolerance(4e-5, None, "per value, relative"),  # 1.5e-5
    "mickey.features-full": Tolerance(1e-5, None, "relative to the array's largest magnitude"),  # 1.3e-6
    "mickey.solver.R": Tolerance(3e-6, None, "absolute"),  # 9.2e-7
    "mickey.solver.t": Tolerance(7e-6, None, "absolute"),  # 2.5e-6
    # Official RPR releases: the regressed pose, absolute.
    "rpr.R": Tolerance(4e-6, None, "absolute"),  # 1.6e-6 (rotquat_trans, portable kernels; the slow configurations)
    "rpr.t": Tolerance(7e-7, None, "absolute"),  # 2.4e-7
}


def vector_errors(got: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Error of each (H, W, C) vector relative to its own length, or of each (H, W) value relative to its size.

    Lengths below 1 % of the map's median are judged against that floor: a point near the camera centre has an
    ill-conditioned direction (float32 sums in another order move it by ~1e-5 of the map's scale).
    """
    assert got.shape == want.shape
    size = np.linalg.norm(want, axis=-1) if want.ndim == 3 else np.abs(want)
    diff = np.linalg.norm(got - want, axis=-1) if want.ndim == 3 else np.abs(got - want)
    return diff / np.maximum(size, 0.01 * np.median(size))


def max_relative(got: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Errors relative to the array's largest magnitude."""
    return np.abs(got - want) / np.abs(want).max()


def elementwise_relative(got: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Per-value relative errors (numpy's ``rtol``); an exact zero must stay an exact zero."""
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    diff = np.abs(got - want)
    return np.where(want == 0, np.where(diff > 0, np.inf, 0.0), diff / np.where(want == 0, 1.0, np.abs(want)))


def absolute(got: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Absolute differences."""
    return np.abs(np.asarray(got, np.float64) - np.asarray(want, np.float64))


def exceeded(kind: str, errors: np.ndarray) -> str | None:
    """How ``errors`` break the tolerance of ``kind``, or None when they keep it."""
    tol = TOLERANCES[kind]
    worst, mean = float(np.max(errors)), float(np.mean(errors))
    if not worst < tol.max:
        return f"largest error {worst:.2e} above the {tol.max:.2g} tolerance of {kind} ({tol.measure})"
    if tol.mean is not None and not mean < tol.mean:
        return f"mean error {mean:.2e} above the {tol.mean:.2g} tolerance of {kind} ({tol.measure})"
    return None


def check(what: str, kind: str, errors: np.ndarray) -> None:
    """Assert ``errors`` keep the tolerance of ``kind`` (or record them, when a spread is being measured)."""
    path = os.environ.get("MAPFREE_FIXTURE_ERRORS")
    if path:
        rec = {"what": what, "kind": kind, "max": float(np.max(errors)), "mean": float(np.mean(errors))}
        with open(path, "a") as f:
            f.write(json.dumps(rec) + "\n")
        return
    problem = exceeded(kind, errors)
    assert problem is None, f"{what}: {problem}"

"""A calibrated probability that a pose is right, fitted per method on frames with ground truth.

``p_correct`` is P(VCRE < 90 px), the benchmark's own criterion; ``p_pose`` is P(error < 25 cm and 5 deg). Both
are read from an estimate's ``Signals`` (and its own confidence) by a monotone, regularised model: a logistic
regression on transformed signals (log counts, ratios, log residual, the scale disagreement ``|log scale_ratio|``)
followed by an isotonic map of its output, fitted with scikit-learn (``fit``) and stored as plain numbers in a JSON
file (``Calibration.save``; no pickle). Applying one (``Calibration.apply``) needs numpy only.

The held-out figures of a file (ECE, Brier score, precision at p >= 0.5/0.8/0.9, reliability bins) come from
cross-validation: each frame's probability there was predicted by a model fitted without it.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from .benchmark.reliability import reliability
from .estimate import Estimate, Signals
from .localizer import BatchOptions, Localizer, ViewLike

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "TARGETS",
    "MIN_FRAMES",
    "CalibrationError",
    "Model",
    "Calibration",
    "features",
    "centred_knots",
    "fit",
    "shipped",
    "calibration_for",
    "CALIBRATION_OPTION",
    "Calibrated",
]

FORMAT = "mapfree-calibration"
FORMAT_VERSION = 1
#: What each fitted probability means.
TARGETS = {"p_correct": "VCRE < 90 px", "p_pose": "translation error < 25 cm and rotation error < 5 deg"}
#: Fewest frames with an estimate a calibration is fitted on.
MIN_FRAMES = 30
#: Key of ``Method.options`` naming a calibration file (``mapfree run --calibration``).
CALIBRATION_OPTION = "calibration"
#: Cross-validation folds of the held-out figures.
FOLDS = 5


class CalibrationError(ValueError):
    """A calibration file that cannot be used, or data a calibration cannot be fitted on (one line)."""


def _log1p(v: float | None) -> float | None:
    return None if v is None else math.log1p(max(float(v), 0.0))


#: Feature name -> how it is read from (signals, the estimate's confidence); None where not measured. Each is
#: monotone in what it measures, so the logistic model's sign per feature reads as "more is better/worse".
_FEATURES: dict[str, Callable[[Signals, float], float | None]] = {
    "confidence": lambda s, c: math.log1p(max(c, 0.0)),
    "n_matches": lambda s, c: _log1p(s.n_matches),
    "n_inliers": lambda s, c: _log1p(s.n_inliers),
    "inlier_ratio": lambda s, c: s.inlier_ratio,
    "score": lambda s, c: _log1p(s.score),
    "residual": lambda s, c: None if s.residual is None else math.log(max(s.residual, 1e-6)),
    "depth_valid_fraction": lambda s, c: s.depth_valid_fraction,
    "scale_error": lambda s, c: None if not s.scale_ratio else abs(math.log(s.scale_ratio)),
    "learned_confidence": lambda s, c: _log1p(s.learned_confidence),
}


def features(signals: Signals, confidence: float, names: Sequence[str] = tuple(_FEATURES)) -> np.ndarray:
    """The model's inputs of one estimate.

    Args:
        signals: The estimate's signals.
        confidence: The estimate's own confidence (>= 0).
        names: Which features, in order.

    Returns:
        (F,) float64, NaN where a signal was not measured.
    """
    out = [_FEATURES[n](signals, float(confidence)) for n in names]
    return np.array([np.nan if v is None else v for v in out], dtype=np.float64)


@dataclass
class Model:
    """One fitted probability: standardised features -> logistic score -> isotonic map to [0, 1].

    Attributes:
        impute: (F,) value used for a feature that was not measured (the training median).
        mean: (F,) standardisation means.
        scale: (F,) standardisation scales.
        coef: (F,) logistic coefficients.
        intercept: Logistic intercept.
        iso_x: Increasing logistic scores of the isotonic map's knots.
        iso_y: Probabilities at the knots (non-decreasing; linear in between, clipped outside).
    """

    impute: list[float]
    mean: list[float]
    scale: list[float]
    coef: list[float]
    intercept: float
    iso_x: list[float]
    iso_y: list[float]

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Probabilities of feature rows.

        Args:
            X: (N, F) features, NaN where not measured.

        Returns:
            (N,) probabilities in [0, 1].
        """
        X = np.where(np.isnan(X), np.asarray(self.impute), X)
        z = ((X - np.asarray(self.mean)) / np.asarray(self.scale)) @ np.asarray(self.coef) + self.intercept
        return np.clip(np.interp(z, self.iso_x, self.iso_y), 0.0, 1.0)

    @classmethod
    def from_dict(cls, d: dict, n_features: int) -> Model:
        m = cls(**{k: d[k] for k in cls.__dataclass_fields__})
        sizes = {len(m.impute), len(m.mean), len(m.scale), len(m.coef)}
        if sizes != {n_features} or len(m.iso_x) != len(m.iso_y) or not m.iso_x:
            raise ValueError("array sizes disagree")
        arrays = [*m.impute, *m.mean, *m.scale, *m.coef, m.intercept, *m.iso_x, *m.iso_y]
        if not all(math.isfinite(float(v)) for v in arrays) or min(m.scale) <= 0:
            raise ValueError("non-finite or non-positive values")
        if any(b < a for a, b in zip(m.iso_x, m.iso_x[1:])) or not all(0 <= v <= 1 for v in m.iso_y):
            raise ValueError("isotonic knots not increasing, or probabilities outside [0, 1]")
        return m


@dataclass
class Calibration:
    """A method's fitted probabilities and their held-out figures (``mapfree calibrate``'s JSON file).

    Attributes:
        method: The method it was fitted for (an estimate of another method is refused).
        signals: The features the models read, in order (``features``).
        frames: Frames with an estimate it was fitted on.
        models: ``p_correct`` and ``p_pose`` (``TARGETS``).
        figures: Per target, the cross-validated ``Reliability.to_dict()`` (ECE, Brier, precision, bins).
        data: Where the frames came from (dataset and split).
        version: The file format's version.
    """

    method: str
    signals: list[str]
    frames: int
    models: dict[str, Model]
    figures: dict[str, dict] = field(default_factory=dict)
    data: str = ""
    version: int = FORMAT_VERSION

    def probabilities(self, est: Estimate) -> dict[str, float]:
        """``p_correct`` and ``p_pose`` of an estimate.

        Args:
            est: An estimate of this calibration's method.

        Returns:
            ``{target: probability}``; 0 for an estimate without a pose.
        """
        if not est.ok:
            return {t: 0.0 for t in self.models}
        x = features(est.signals, est.confidence, self.signals)[None]
        return {t: float(m.predict(x)[0]) for t, m in self.models.items()}

    def p_correct(self, signals: Signals | dict, confidence: float) -> float:
        """``p_correct`` of an estimate's signals (as a journal records them) and confidence.

        Args:
            signals: ``Signals`` or their ``to_dict()``.
            confidence: The estimate's own confidence.

        Returns:
            The probability.
        """
        s = signals if isinstance(signals, Signals) else Signals.from_dict(signals)
        return float(self.models["p_correct"].predict(features(s, confidence, self.signals)[None])[0])

    def apply(self, est: Estimate) -> Estimate:
        """Set ``est.p_correct`` (and ``extras["p_pose"]``) from this calibration; an estimate without a pose is
        left without.

        Args:
            est: The estimate, changed in place.

        Returns:
            ``est``.
        """
        if est.ok:
            p = self.probabilities(est)
            est.p_correct = p["p_correct"]
            if "p_pose" in p:
                est.extras["p_pose"] = p["p_pose"]
        return est

    def to_dict(self) -> dict[str, Any]:
        """The JSON file's content.

        Returns:
            ``format``, ``version``, ``method``, ``targets``, ``signals``, ``frames``, ``data``, ``models``,
                ``figures``.
        """
        return {
            "format": FORMAT,
            "version": self.version,
            "method": self.method,
            "targets": TARGETS,
            "signals": self.signals,
            "frames": self.frames,
            "data": self.data,
            "models": {k: asdict(m) for k, m in self.models.items()},
            "figures": self.figures,
        }

    def save(self, path: os.PathLike | str) -> None:
        """Write the JSON file.

        Args:
            path: Where.
        """
        Path(path).write_text(json.dumps(self.to_dict(), indent=1, allow_nan=False) + "\n")

    @classmethod
    def load(cls, path: os.PathLike | str, method: str | None = None) -> Calibration:
        """Read a calibration file.

        Args:
            path: The JSON file.
            method: The method it must have been fitted for (None: any).

        Returns:
            The calibration.

        Raises:
            CalibrationError: Missing, corrupt, another format or version, or fitted for another method.
        """
        path = Path(path)
        try:
            text = path.read_bytes()
        except FileNotFoundError:
            raise CalibrationError(f"calibration {path} not found") from None
        except OSError as e:
            raise CalibrationError(f"calibration {path} is not readable JSON ({e})") from None
        return cls.from_json(text, str(path), method)

    @classmethod
    def from_json(cls, text: str | bytes, where: str, method: str | None = None) -> Calibration:
        """``from_dict`` of a file's JSON text (an upload to the service); ``CalibrationError`` also when it is no
        readable JSON."""
        try:
            d = json.loads(text)
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
            raise CalibrationError(f"calibration {where} is not readable JSON ({e})") from None
        return cls.from_dict(d, where, method)

    @classmethod
    def from_dict(cls, d: Any, where: str, method: str | None = None) -> Calibration:
        """A calibration from a file's parsed JSON (``to_dict``), with the same checks as ``load``.

        Args:
            d: The parsed JSON.
            where: What the messages call it (the file's name).
            method: The method it must have been fitted for (None: any).

        Returns:
            The calibration.

        Raises:
            CalibrationError: Corrupt, another format or version, or fitted for another method.
        """
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise CalibrationError(f"calibration {where} is not a mapfree calibration file (no format {FORMAT!r})")
        if d.get("version") != FORMAT_VERSION:
            raise CalibrationError(
                f"calibration {where} has format version {d.get('version')!r}, this mapfree reads version "
                f"{FORMAT_VERSION}: fit it again with `mapfree calibrate`"
            )
        try:
            names = [str(n) for n in d["signals"]]
            unknown = [n for n in names if n not in _FEATURES]
            if unknown:
                raise ValueError(f"unknown signal(s) {', '.join(unknown)}")
            models = {t: Model.from_dict(d["models"][t], len(names)) for t in TARGETS}
            cal = cls(str(d["method"]), names, int(d["frames"]), models, dict(d.get("figures", {})), str(d["data"]))
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            what = f"missing {e}" if isinstance(e, KeyError) else str(e)
            raise CalibrationError(f"calibration {where} is corrupt: {what}") from None
        if method is not None and cal.method != method:
            raise CalibrationError(
                f"calibration {where} was fitted for method {cal.method!r}, not {method!r}: "
                f"fit one for {method!r} with `mapfree calibrate DATA --method {method}`"
            )
        return cal


# --------------------------------------------------------------------------- fitting


def _fit_model(X: np.ndarray, y: np.ndarray) -> Model:
    from sklearn.isotonic import IsotonicRegression
    from sklearn.linear_model import LogisticRegression

    impute = np.nanmedian(X, axis=0)
    impute = np.where(np.isfinite(impute), impute, 0.0)
    Xi = np.where(np.isnan(X), impute, X)
    mean, scale = Xi.mean(axis=0), Xi.std(axis=0)
    scale = np.where(scale > 1e-12, scale, 1.0)
    Z = (Xi - mean) / scale
    lr = LogisticRegression(C=1.0, max_iter=1000).fit(Z, y)
    z = Z @ lr.coef_[0] + lr.intercept_[0]
    iso = IsotonicRegression(y_min=0.0, y_max=1.0, increasing=True, out_of_bounds="clip").fit(z, y)
    knots_x, knots_y = centred_knots(iso.X_thresholds_, iso.y_thresholds_)
    return Model(
        impute.tolist(),
        mean.tolist(),
        scale.tolist(),
        lr.coef_[0].tolist(),
        float(lr.intercept_[0]),
        [float(v) for v in knots_x],
        [float(v) for v in knots_y],
    )


def centred_knots(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centred isotonic regression: one knot per constant block of an isotonic fit, at the block's centre, so that
    the map interpolates between blocks instead of holding each one flat.

    A flat block gives every frame in it the same probability, and the benchmark's AUC ranks by the probability:
    ties there lose the ranking the logistic score had (a cascade ranks by nothing else). Between block centres
    the map rises strictly, so frames keep the logistic score's order; each block's level is unchanged.

    Args:
        x: (K,) the isotonic fit's increasing thresholds (``X_thresholds_``).
        y: (K,) its non-decreasing values there (``y_thresholds_``).

    Returns:
        (B,) strictly increasing knot positions and (B,) their values, one per block.
    """
    starts = np.flatnonzero(np.r_[True, np.diff(y) != 0])
    ends = np.r_[starts[1:] - 1, len(y) - 1]
    return (x[starts] + x[ends]) / 2.0, y[starts]


def _held_out(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Each frame's probability from a model fitted on the other folds (stratified, seeded)."""
    from sklearn.model_selection import StratifiedKFold

    folds = min(FOLDS, int(min(y.sum(), (~y).sum())))
    p = np.empty(len(y))
    for train, test in StratifiedKFold(folds, shuffle=True, random_state=0).split(X, y):
        p[test] = _fit_model(X[train], y[train]).predict(X[test])
    return p


def _check_classes(y: np.ndarray, target: str, where: str) -> None:
    n_right = int(y.sum())
    if n_right < 2 or len(y) - n_right < 2:
        raise CalibrationError(
            f"{where}: {n_right} of {len(y)} frames have {TARGETS[target]}: a calibration needs at least 2 frames "
            f"right and 2 wrong (one class only cannot be fitted)"
        )


def fit(
    method: str,
    signals: Sequence[Signals],
    confidence: Sequence[float],
    vcre_px: np.ndarray,
    trans_err_m: np.ndarray,
    rot_err_deg: np.ndarray,
    data: str = "",
) -> Calibration:
    """Fit ``p_correct`` and ``p_pose`` of a method on its estimates of frames with ground truth.

    Args:
        method: The method's name.
        signals: (N) each estimate's signals (frames with an estimate only).
        confidence: (N) each estimate's own confidence.
        vcre_px: (N,) VCRE of each estimate, pixels.
        trans_err_m: (N,) translation error, metres.
        rot_err_deg: (N,) rotation error, degrees.
        data: Where the frames came from, recorded in the file.

    Returns:
        The calibration, with cross-validated figures.

    Raises:
        CalibrationError: Fewer than ``MIN_FRAMES`` estimates, or one class only (or one frame of a class).
    """
    n = len(signals)
    where = data or method
    if n < MIN_FRAMES:
        raise CalibrationError(
            f"{where}: {n} frames with an estimate, a calibration needs at least {MIN_FRAMES} (use a larger split)"
        )
    X_all = np.stack([features(s, c) for s, c in zip(signals, confidence)])
    measured = np.isfinite(X_all)
    names = list(_FEATURES)
    keep = [
        i
        for i in range(len(names))
        if measured[:, i].mean() >= 0.5 and np.nanstd(np.where(measured[:, i], X_all[:, i], np.nan)) > 1e-9
    ]
    if not keep:
        keep = [0]  # the confidence alone: constant, so the model is the base rate
    X = X_all[:, keep]
    outcomes = {
        "p_correct": np.asarray(vcre_px) < 90.0,
        "p_pose": (np.asarray(trans_err_m) < 0.25) & (np.asarray(rot_err_deg) < 5.0),
    }
    models: dict[str, Model] = {}
    figures: dict[str, dict] = {}
    for target, y in outcomes.items():
        _check_classes(y, target, where)
        models[target] = _fit_model(X, y)
        figures[target] = reliability(_held_out(X, y), y).to_dict()
    return Calibration(method, [names[i] for i in keep], n, models, figures, data)


# --------------------------------------------------------------------------- shipped calibrations


def _shipped_dir() -> Path:
    return Path(__file__).resolve().parent / "configs" / "calibration"


def shipped(method: str) -> Path | None:
    """The calibration file shipped for a preset (``configs/calibration/NAME.calib.json``), if any.

    Args:
        method: The preset's name.

    Returns:
        The file, or None.
    """
    p = _shipped_dir() / f"{method}.calib.json"
    return p if p.is_file() else None


@lru_cache(maxsize=32)
def _load_cached(path: str, method: str) -> Calibration:
    return Calibration.load(path, method)


def calibration_for(method: str, options: dict[str, Any] | None = None) -> Calibration | None:
    """The calibration a method's estimates get: the file in its options (``--calibration``), else the one shipped
    for the preset, else None.

    Args:
        method: The method's name.
        options: The method's options (``CALIBRATION_OPTION``).

    Returns:
        The calibration, or None.

    Raises:
        CalibrationError: The named file cannot be used for this method.
    """
    path = (options or {}).get(CALIBRATION_OPTION) or shipped(method)
    return None if path is None else _load_cached(str(path), method)


# --------------------------------------------------------------------------- the API's wrapper


class Calibrated(Localizer[Any]):
    """A localizer whose estimates carry ``p_correct`` (and ``extras["p_pose"]``) from a calibration.

    Args:
        localizer: The method's localizer (``Method.build()``, ``mapfree.relocalize.build_localizer``).
        calibration: The method's calibration.
    """

    def __init__(self, localizer: Localizer[Any], calibration: Calibration) -> None:
        self.localizer, self.calibration = localizer, calibration

    def set_reference(self, reference: Any) -> Any:
        return self.localizer.set_reference(reference)

    def prepare(self, reference: Any) -> Any:
        return self.localizer.prepare(reference)

    def localize(self, query: ViewLike, anchor: Any | None = None) -> Estimate:
        return self.calibration.apply(self.localizer.localize(query, anchor))

    def localize_many(
        self, queries: Iterable[ViewLike], anchor: Any | None = None, *, prefetch: int = 1
    ) -> Iterable[Estimate]:
        return (self.calibration.apply(e) for e in self.localizer.localize_many(queries, anchor, prefetch=prefetch))

    def localize_batched(
        self, queries: Iterable[ViewLike], *, anchor: Any | None = None, options: BatchOptions | None = None
    ) -> Iterable[Estimate]:
        batched = self.localizer.localize_batched(queries, anchor=anchor, options=options)
        return (self.calibration.apply(e) for e in batched)

    def default_batch_size(self) -> int:
        return self.localizer.default_batch_size()

    def check_available(self) -> None:
        self.localizer.check_available()

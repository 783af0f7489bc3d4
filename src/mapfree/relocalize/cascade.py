"""A cascade: methods tried in order, each only where the ones before it are not sure enough.

``{kind: cascade, stages: [A, B, C], accept: 0.8}`` (a method YAML), or ``A+B+C`` on the command line
(accept 0.8), runs A on a query; only when A's calibrated probability ``p_correct`` is below ``accept`` (or A has
no estimate) does it run B, then C. It answers with the estimate of highest probability among the stages it ran
(an estimate whenever any of them has one), its confidence that probability, and ``Estimate.stage`` naming the
stage. Each stage needs a calibration: the file given for it (``mapfree run --calibration``, once per stage) or
the one shipped with the preset (``mapfree.calibration.shipped``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from ..calibration import CALIBRATION_OPTION, Calibration, CalibrationError, calibration_for
from ..estimate import Estimate
from ..localizer import Localizer, ViewLike
from ..methods import CASCADE, CASCADE_SEPARATOR, DEFAULT_ACCEPT, Method, check_cascade_options, get

__all__ = ["CASCADE", "CASCADE_SEPARATOR", "STAGE_CALIBRATIONS", "build_cascade", "Cascade"]

#: Key of a cascade's ``Method.options``: ``{stage name: calibration file}`` (``mapfree run --calibration``).
STAGE_CALIBRATIONS = "stage_calibrations"


class Cascade(Localizer[tuple]):
    """The cascade's localizer: one localizer and calibration per stage.

    Args:
        names: The stages' method names.
        stages: Their localizers.
        calibrations: Their calibrations.
        accept: Stop at the first stage whose ``p_correct`` is at least this.
    """

    def __init__(
        self, names: Sequence[str], stages: Sequence[Localizer[Any]], calibrations: Sequence[Calibration], accept: float
    ) -> None:
        self.names, self.stages, self.calibrations = list(names), list(stages), list(calibrations)
        self.accept = float(accept)
        self._anchors: tuple | None = None

    def with_calibrations(self, calibrations: Mapping[str, Calibration]) -> Cascade:
        """The same stages (shared, not rebuilt) with some stages' calibrations replaced: what the relocalization
        service does for an anchor given its own calibrations.

        Args:
            calibrations: ``{method name: calibration}``; a stage not named keeps its own.

        Returns:
            A cascade with the same accept threshold and no current reference.
        """
        cals = [calibrations.get(get(n).name, c) for n, c in zip(self.names, self.calibrations)]
        return Cascade(self.names, self.stages, cals, self.accept)

    def stage_methods(self) -> list[str]:
        """The stages' registered method names (what a calibration names), in order."""
        return [get(n).name for n in self.names]

    def set_reference(self, reference: Any) -> tuple:
        self._anchors = tuple(s.set_reference(reference) for s in self.stages)
        return self._anchors

    def prepare(self, reference: Any) -> tuple:
        return tuple(s.prepare(reference) for s in self.stages)

    def localize(self, query: ViewLike, anchor: tuple | None = None) -> Estimate:
        """The estimate of highest ``p_correct`` among the stages run (see the module's description).

        Args:
            query: A ``ViewLike``.
            anchor: A ``prepare``'d reference (default: the current one).

        Returns:
            The estimate, its confidence its ``p_correct``, ``stage`` the stage's name, ``timings`` the stages'
                totals (``total`` their sum, ``stage:NAME`` each); without any stage's estimate, the stages'
                reasons.
        """
        anchors = anchor if anchor is not None else self._anchors
        if anchors is None:
            return Estimate.failure("no reference: call set_reference or pass a prepared anchor")
        best: Estimate | None = None
        reasons: list[str] = []
        timings: dict[str, float] = {}
        for name, loc, cal, a in zip(self.names, self.stages, self.calibrations, anchors):
            est = cal.apply(loc.localize(query, a))
            seconds = float(est.timings.get("total", sum(est.timings.values())))
            timings[f"stage:{name}"] = seconds
            if not est.ok:
                reasons.append(f"{name}: {est.reason}")
                continue
            p = est.p_correct if est.p_correct is not None else 0.0
            if best is None or p > (best.p_correct or 0.0):
                best, est.stage = est, name
            if p >= self.accept:
                break
        timings["total"] = math.fsum(v for k, v in timings.items() if k.startswith("stage:"))
        if best is None:
            return Estimate.failure("; ".join(reasons), **timings)
        best.confidence = best.p_correct or 0.0
        best.timings = {**{k: v for k, v in best.timings.items() if k != "total"}, **timings}
        return best

    def check_available(self) -> None:
        for s in self.stages:
            s.check_available()


def build_cascade(method: Method) -> Cascade:
    """The factory of the ``cascade`` kind (``methods.KINDS``): each stage built, with its calibration.

    Args:
        method: A cascade ``Method``.

    Returns:
        The localizer.

    Raises:
        CalibrationError: A stage without a calibration (none given, none shipped).
    """
    check_cascade_options(method.options, method.name)
    names = [str(s) for s in method.options["stages"]]
    files = dict(method.options.get(STAGE_CALIBRATIONS, {}))
    stages, calibrations = [], []
    for name in names:
        stage = get(name)
        cal = calibration_for(stage.name, {CALIBRATION_OPTION: files.get(name)} if files.get(name) else None)
        if cal is None:
            raise CalibrationError(
                f"cascade {method.name!r}: stage {name!r} has no calibration (none shipped): fit one with `mapfree "
                f"calibrate DATA --method {name} -o {name}.calib.json` and pass --calibration {name}.calib.json"
            )
        stages.append(stage.build())
        calibrations.append(cal)
    return Cascade(names, stages, calibrations, float(method.options.get("accept", DEFAULT_ACCEPT)))

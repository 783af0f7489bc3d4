"""Cascades of presets judged with held-out probabilities, from runs already made (no method runs here).

Usage:

    python bench/cascade_heldout.py --accept 0.8 \
        METHOD=ROOT:JOURNAL[,ROOT:JOURNAL ...] [METHOD=... ...] --cascade A+B [--cascade B+A ...]

Each JOURNAL is a ``mapfree run --all-frames`` journal of METHOD on ROOT's val split (``mapfree calibrate`` leaves
one beside its output). Every frame's ``p_correct`` comes from a calibration fitted (``mapfree.calibration.fit``)
on the frames of all the other scenes, of every dataset: a cascade here never ranks or stops by a probability
fitted on its own scene. A cascade is replayed per frame as ``mapfree.relocalize.cascade.Cascade`` runs it:
stage after stage until one's probability reaches ``--accept``, answering with the highest probability among the
stages run; its seconds are the sum of those stages' journaled ``total`` seconds (each stage's own run, so the
times are as comparable as the runs' machine load was). The table gives, over the frames every method's journal
has, and then per dataset: AUC @ VCRE < 90 px (the benchmark's ranking metric, frames without an estimate counted),
frames right, seconds per frame, for each method alone (ranked by its own confidence, and by its held-out
``p_correct``) and for each cascade.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapfree.benchmark.metrics import auc
from mapfree.calibration import CalibrationError, fit
from mapfree.relocalize import read_journal
from mapfree.relocalize.calibrate import journal_frames

Key = tuple[str, str, str]  # (dataset, scene, frame)


@dataclass
class Outcome:
    """One method's answer on one frame."""

    seconds: float
    ok: bool = False
    right: bool = False
    confidence: float = 0.0
    p: float = 0.0


def outcomes(method: str, pairs: Sequence[tuple[str, str]]) -> dict[Key, Outcome]:
    """Every frame of a method's journals, with the leave-one-scene-out ``p_correct`` of those with an estimate."""
    out: dict[Key, Outcome] = {}
    keys: list[Key] = []
    sig, conf, vcre, te, re = [], [], [], [], []
    for root, journal in pairs:
        data = Path(root).name
        frames = journal_frames(journal, root, "val")
        _, recs = read_journal(journal)
        for r in recs:
            out[(data, r["scene"], r["frame"])] = Outcome(float(r["timings"].get("total", 0.0)))
        keys += [(data, r["scene"], r["frame"]) for r in recs if r["ok"]]
        sig += frames.signals
        conf += frames.confidence.tolist()
        vcre += frames.vcre.tolist()
        te += frames.trans_err.tolist()
        re += frames.rot_err.tolist()
    scene = np.array([f"{k[0]}/{k[1]}" for k in keys])
    for s in sorted(set(scene)):
        train = np.flatnonzero(scene != s)
        try:
            cal = fit(
                method,
                [sig[i] for i in train],
                [conf[i] for i in train],
                np.array(vcre)[train],
                np.array(te)[train],
                np.array(re)[train],
            )
        except CalibrationError as e:
            print(f"{method} without {s}: {e}")
            continue
        for i in np.flatnonzero(scene == s):
            o = out[keys[i]]
            o.ok, o.right, o.confidence = True, bool(vcre[i] < 90.0), float(conf[i])
            o.p = cal.p_correct(sig[i], conf[i])
    return out


def cascade(stages: Sequence[dict[Key, Outcome]], accept: float, key: Key) -> tuple[Outcome | None, float]:
    """A cascade's answer on one frame (the estimate of highest p among the stages run) and its seconds."""
    best, seconds = None, 0.0
    for stage in stages:
        o = stage[key]
        seconds += o.seconds
        if o.ok and (best is None or o.p > best.p):
            best = o
        if o.ok and o.p >= accept:
            break
    return best, seconds


def row(name: str, answers: Sequence[tuple[Outcome | None, float]], by: str) -> str:
    """One line of the table: frames, AUC, frames right, seconds per frame."""
    got = [a for a, _ in answers if a is not None and a.ok]
    conf = np.array([a.p if by == "p" else a.confidence for a in got])
    right = np.array([a.right for a in got], dtype=bool)
    a = float(auc(conf, right, len(answers) - len(got))) if got else 0.0
    seconds = float(np.mean([s for _, s in answers]))
    return f"| {name} | {len(answers)} | {a:.3f} | {int(right.sum())} | {seconds:.2f} |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="METHOD=ROOT:JOURNAL[,ROOT:JOURNAL ...]")
    ap.add_argument("--cascade", action="append", default=[], help="stages joined by + (repeat)")
    ap.add_argument("--accept", type=float, default=0.8)
    args = ap.parse_args()
    methods = {}
    for spec in args.runs:
        name, rest = spec.split("=", 1)
        methods[name] = outcomes(name, [tuple(p.split(":", 1)) for p in rest.split(",")])
    keys = sorted(set.intersection(*(set(m) for m in methods.values())))
    for data in [None, *sorted({k[0] for k in keys})]:
        sel = [k for k in keys if data is None or k[0] == data]
        print(f"\n{data or 'all datasets'} ({len(sel)} frames), accept {args.accept:g}, held-out p_correct\n")
        print("| method | frames | AUC @ VCRE < 90 px | right | s / frame |")
        print("|---|---:|---:|---:|---:|")
        for name, m in methods.items():
            answers = [(m[k], m[k].seconds) for k in sel]
            print(row(f"{name} (own confidence)", answers, "confidence"))
            print(row(f"{name} (p_correct)", answers, "p"))
        for c in args.cascade:
            stages = [methods[s] for s in c.split("+")]
            print(row(f"cascade {c}", [cascade(stages, args.accept, k) for k in sel], "p"))


if __name__ == "__main__":
    main()

"""Calibration on scenes it never saw: each scene's probabilities from a calibration fitted on the other scenes.

Usage:

    python bench/calibration_heldout.py METHOD ROOT:JOURNAL [ROOT:JOURNAL ...]

Each JOURNAL is a ``mapfree run --all-frames`` journal of METHOD on ROOT's val split (``mapfree calibrate`` leaves
one beside its output, ``NAME.calib.run.journal.jsonl``). For every scene, a calibration is fitted on the frames
of all the other scenes (every dataset) and predicts that scene's frames; the table gives, per dataset, the ECE
(10 bins), the Brier score and the precision of the frames with p >= 0.9 of these leave-one-scene-out
probabilities: the closest this data comes to a calibration used on new scenes. The last column is the ECE that
perfectly calibrated probabilities would show on as many frames: the mean over 500 draws of outcomes drawn from
these same probabilities (the ECE of a few dozen frames is mostly noise; an observed ECE near it is as good as this
many frames can show).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mapfree.benchmark.reliability import reliability
from mapfree.calibration import CalibrationError, fit
from mapfree.estimate import Signals
from mapfree.relocalize import read_journal
from mapfree.relocalize.calibrate import journal_frames


def main() -> None:
    method, pairs = sys.argv[1], [a.split(":", 1) for a in sys.argv[2:]]
    sig: list[Signals] = []
    conf, vcre, te, re, scene, data = [], [], [], [], [], []
    for root, journal in pairs:
        f = journal_frames(journal, root, "val")
        _, recs = read_journal(journal)
        names = [r["scene"] for r in recs if r["ok"]]
        sig += f.signals
        conf += f.confidence.tolist()
        vcre += f.vcre.tolist()
        te += f.trans_err.tolist()
        re += f.rot_err.tolist()
        scene += [f"{Path(root).name}/{s}" for s in names]
        data += [Path(root).name] * len(names)
    vcre_a, scene_a, data_a = np.array(vcre), np.array(scene), np.array(data)
    p = np.full(len(sig), np.nan)
    for s in sorted(set(scene)):
        out = scene_a == s
        idx = np.flatnonzero(~out)
        try:
            cal = fit(
                method, [sig[i] for i in idx], [conf[i] for i in idx], vcre_a[idx], np.array(te)[idx], np.array(re)[idx]
            )
        except CalibrationError as e:
            print(f"{s}: {e}")
            continue
        for i in np.flatnonzero(out):
            p[i] = cal.p_correct(sig[i], conf[i])
    print(f"\n{method}: leave-one-scene-out p_correct\n")
    print("| data | frames | ECE | Brier | accepted at p >= 0.9 | precision at p >= 0.9 | ECE if calibrated |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    rng = np.random.default_rng(0)
    for d in [*sorted(set(data)), "all"]:
        sel = np.isfinite(p) & ((data_a == d) if d != "all" else True)
        r = reliability(p[sel], vcre_a[sel] < 90)
        prec = "-" if r.precision[0.9] is None else f"{r.precision[0.9]:.3f}"
        floor = np.mean([reliability(p[sel], rng.uniform(size=sel.sum()) < p[sel]).ece for _ in range(500)])
        print(f"| {d} | {r.frames} | {r.ece:.3f} | {r.brier:.3f} | {r.accepted[0.9]} | {prec} | {floor:.3f} |")


if __name__ == "__main__":
    main()

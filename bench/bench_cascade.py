"""Each stage alone against a cascade of them: AUC, precision and seconds per frame, in one run.

Usage (each run is journaled under OUT and resumed, so a second call only recomputes the table):

    python bench/bench_cascade.py OUT ROOT [ROOT ...] --stages best-offline,aliked-lightglue_procrustes_sensor \
        [--accept 0.8] [--calibration FILE ...]

Every query of every ROOT's val split with ground truth is relocalized (not only the scored fifth: realmini-dev
has 20 scored frames), by each stage alone and by the cascade ``A+B``. Per method the table gives: frames, the
fraction with an estimate, AUC @ VCRE < 90 px (the benchmark's ranking metric, failures counted), precision @ VCRE
< 90 px, and the mean of the journal's per-frame ``total`` seconds (the method's own compute: reading, matching,
depth, solving; not the process start). The cascade ranks by its ``p_correct``, each stage by its own confidence
and by its calibrated ``p_correct``. The calibrations are those passed (else the shipped ones): when they were
fitted on the same frames the cascade's figures are in-sample.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mapfree.benchmark.metrics import auc
from mapfree.calibration import Calibration, calibration_for
from mapfree.methods import get
from mapfree.relocalize import read_journal, run_split
from mapfree.relocalize.calibrate import journal_frames, with_calibration


def _figures(root: Path, journal: Path, key: str, calibration: Calibration | None = None) -> dict:
    """Per-frame outcomes of a journal: confidences (``key``: confidence or p_correct, from ``calibration`` and
    the journaled signals when given), right, seconds."""
    _, recs = read_journal(journal)
    frames = journal_frames(journal, root, "val")
    if calibration is not None:
        conf = np.array([calibration.p_correct(s, c) for s, c in zip(frames.signals, frames.confidence)])
    else:
        conf = np.nan_to_num(frames.p_correct) if key == "p_correct" else frames.confidence
    seconds = np.array([r["timings"].get("total", 0.0) for r in recs])
    return {
        "conf": conf,
        "right": frames.vcre < 90.0,
        "failed": frames.failed,
        "seconds": seconds,
        "stages": frames.stage,
        "recs": recs,
    }


def _row(name: str, parts: list[dict]) -> str:
    conf = np.concatenate([p["conf"] for p in parts])
    right = np.concatenate([p["right"] for p in parts])
    failed = sum(p["failed"] for p in parts)
    seconds = np.concatenate([p["seconds"] for p in parts])
    n = len(conf) + failed
    a = float(auc(conf, right, failed)) if len(conf) else 0.0
    prec = float(right.sum() / n) if n else 0.0
    return f"| {name} | {n} | {len(conf) / n:.1%} | {a:.3f} | {prec:.3f} | {seconds.mean():.2f} |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="folder of the runs (resumed)")
    ap.add_argument("roots", type=Path, nargs="+", help="datasets with a val split with poses")
    ap.add_argument("--stages", required=True, help="comma-separated method names, in cascade order")
    ap.add_argument("--accept", type=float, default=0.8)
    ap.add_argument("--calibration", type=Path, action="append", default=[], help="one per stage (else shipped)")
    args = ap.parse_args()
    stages = [s for s in args.stages.split(",") if s]
    cascade = with_calibration(get("+".join(stages)), args.calibration)
    from dataclasses import replace

    cascade = replace(cascade, options={**cascade.options, "accept": args.accept})
    files = cascade.options.get("stage_calibrations", {})
    methods = [with_calibration(get(s), [files[s]]) if s in files else get(s) for s in stages]
    rows: dict[str, list[dict]] = {}
    for i, root in enumerate(args.roots):
        for m in [*methods, cascade]:
            tag = "cascade" if m.kind == "cascade" else m.name
            out = args.out / f"{i}-{root.name}" / f"{tag.replace(':', '_')}.zip"
            out.parent.mkdir(parents=True, exist_ok=True)
            res = run_split(root, "val", m, out, all_frames=True, resume=True, progress=False)
            if m.kind == "cascade":
                f = _figures(root, res.journal, "p_correct")
                rows.setdefault(f"cascade (accept {args.accept:g})", []).append(f)
                used = {s: f["stages"].count(s) for s in stages}
                print(f"{root.name}: cascade answers by stage: {used}")
            else:
                rows.setdefault(f"{m.name} (own confidence)", []).append(_figures(root, res.journal, "confidence"))
                cal = calibration_for(m.name, m.options)
                rows.setdefault(f"{m.name} (p_correct)", []).append(_figures(root, res.journal, "p_correct", cal))
    print(f"\nAll val frames of {', '.join(r.name for r in args.roots)}; stages {', '.join(stages)}\n")
    print("| method | frames | estimated | AUC @ VCRE < 90 px | precision @ 90 px | s / frame |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, parts in rows.items():
        print(_row(name, parts))
    # The cascade's own journal times each stage it ran: the ratio to its first stage is measured in one run.
    recs = [r for p in rows[f"cascade (accept {args.accept:g})"] for r in p["recs"]]
    first = np.mean([r["timings"].get(f"stage:{stages[0]}", 0.0) for r in recs])
    total = np.mean([r["timings"].get("total", 0.0) for r in recs])
    ran = {s: sum(f"stage:{s}" in r["timings"] for r in recs) for s in stages}
    print(
        f"\ncascade: frames each stage ran on {ran}; {total:.2f} s per frame, {total / first:.2f}x its first stage "
        f"({first:.2f} s per frame in the same run)"
    )


if __name__ == "__main__":
    main()

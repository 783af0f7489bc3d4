"""``mapfree demo``: the main job end to end on an embedded default — synthesise, relocalize, score, plot."""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Mapping
from pathlib import Path

from . import DefaultsHelpFormatter

# On monocular depth (the realistic case) PnP, which needs the depth of the reference only, ranks best on
# synthetic val: AUC @ VCRE < 90px 0.952 against 0.864 for best-offline (Procrustes) and 0.769 for Ess.Mat.
DEFAULT_METHOD = "best-offline-pnp@mono"
DEFAULTS = {"scenes": 4, "queries": 30, "seed": 0, "method": DEFAULT_METHOD, "all_frames": False}

#: What the default demo scores on any working install (the data is the same bytes everywhere; measured on CPU):
#: metric -> (value, tolerance). Simulated monocular depth errs by about 10% in scale, so fewer than half of the
#: frames fall within 90 px; with the ground-truth depth (``--method best-offline-pnp@sensor``) nearly all do.
EXPECTED = {
    "Estimates for % of frames": (1.0, 0.0),
    "AUC @ VCRE < 90px": (0.761, 0.06),
    "Precision @ VCRE < 90px": (0.417, 0.1),
}


def expectation(args: argparse.Namespace, metrics: Mapping[str, float | None]) -> list[str]:
    """What the user should expect to see, and whether the run shows it: the lines the demo prints after its table,
    so a broken install (wrong weights, a broken OpenCV or torch) can be told from a working one."""
    lines = [
        "What to expect: with the default settings every one of the 24 scored frames gets an estimate, "
        "AUC @ VCRE < 90px is about 0.76 and precision @ VCRE < 90px about 0.42 (the depth is a simulated "
        "monocular estimate, about 10% off in scale; `--method best-offline-pnp@sensor` uses the true depth)."
    ]
    used = {
        "scenes": args.scenes,
        "queries": args.queries,
        "seed": args.seed,
        "method": args.method,
        "all_frames": args.all_frames,
    }
    changed = [f"--{k.replace('_', '-')} {v}" for k, v in used.items() if v != DEFAULTS[k]]
    if changed:
        lines.append(f"This run changed {', '.join(changed)}: its numbers need not match these.")
        return lines
    got = {k: float("nan") if (x := metrics.get(k)) is None else x for k in EXPECTED}
    off = [
        f"{k} {got[k]:.3f} (expected {v:.3f} ± {tol:.2f})"
        for k, (v, tol) in EXPECTED.items()
        if not abs(got[k] - v) <= tol + 1e-9
    ]
    if off:
        lines.append(
            "UNEXPECTED: " + "; ".join(off) + ". Something in this install differs from a working one: "
            "check `mapfree weights xfeat` and the installed opencv-python and torch versions."
        )
    else:
        lines.append("This run matches: the install works.")
    return lines


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="generate a small synthetic val split, relocalize it with the best offline method, score it, plot it",
        description=(
            "The whole mapfree flow on data it makes itself: a synthetic Map-free val split (real textures, metric "
            "ground truth and a simulated monocular depth), relocalization of every scored query against its "
            "scene's reference, the benchmark's scores, and the paper's plots. Needs no dataset and no network. "
            "After the scores it says what a working install scores on this data, and whether this run does."
        ),
        epilog="examples:\n"
        "  mapfree demo\n"
        "  mapfree demo --out demo-big --scenes 10 --queries 40 --workers 2\n"
        "  mapfree demo --method sift_pnp_mono   # another method on the same simulated depth\n",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder")
    p.add_argument("--scenes", type=int, default=DEFAULTS["scenes"], help="synthetic val scenes")
    p.add_argument("--queries", type=int, default=DEFAULTS["queries"], help="queries per scene (every 5th is scored)")
    p.add_argument("--seed", type=int, default=DEFAULTS["seed"], help="seed of the synthetic split")
    p.add_argument(
        "--method",
        default=DEFAULT_METHOD,
        help="method name (see `mapfree run --list-methods`); '@mono' uses the simulated monocular depth, "
        "'@sensor' the ground-truth depth",
    )
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes for relocalization")
    p.add_argument("--all-frames", action="store_true", help="relocalize every query, not only the scored ones")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..benchmark import evaluate, format_table, save_plots
    from ..data.synth import SynthOptions, generate
    from ..relocalize.run import run_split
    from . import fail, output_folder_problem

    bad = next(
        (
            f"--{k} must be >= 1, got {getattr(args, k)}"
            for k in ("scenes", "queries", "workers")
            if getattr(args, k) < 1
        ),
        None,
    ) or output_folder_problem("--out", args.out)
    if bad:
        return fail("demo", bad)
    out: Path = args.out
    data = out / "data"
    t0 = time.perf_counter()
    stamp = data / "val" / ".demo.json"
    params = {"scenes": args.scenes, "queries": args.queries, "seed": args.seed}
    if stamp.is_file() and json.loads(stamp.read_text()) == params:
        print(f"[1/4] synthetic split already in {data} (same parameters), reusing it")
    else:
        print(f"[1/4] generating {args.scenes} synthetic val scenes x {args.queries} queries in {data}")
        generate(
            data,
            "val",
            n_scenes=args.scenes,
            n_queries=args.queries,
            seed=args.seed,
            options=SynthOptions(queries=args.queries),
        )
        stamp.write_text(json.dumps(params))

    sub = out / "submission.zip"
    print(f"[2/4] relocalizing with {args.method!r}")
    from ..data import FormatError
    from . import EXIT_NOTHING

    try:
        res = run_split(data, "val", args.method, sub, workers=args.workers, all_frames=args.all_frames, overwrite=True)
    except (FileNotFoundError, FormatError, KeyError, ValueError) as e:
        return fail("demo", e)
    print(
        f"      {res.estimated} estimates, {res.failed} without estimate, {res.seconds:.1f} s "
        f"(failures logged in {res.failures})"
    )

    print("[3/4] scoring")
    report = evaluate(sub, data, "val")
    (out / "scores.json").write_text(report.to_json())
    print(format_table(report))
    for line in expectation(args, report.metrics):
        print(line)

    print("[4/4] plotting")
    plots = save_plots(report, out / "plots")
    print(f"\nDone in {time.perf_counter() - t0:.0f} s.")
    print(f"  submission: {sub}")
    print(f"  scores:     {out / 'scores.json'}")
    for p in plots:
        print(f"  plot:       {p}")
    return EXIT_NOTHING if res.estimated == 0 else 0

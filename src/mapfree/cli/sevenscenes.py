"""``mapfree sevenscenes ROOT --method NAME --k 1,10 --out DIR``: the paper's 7-Scenes evaluation (Fig. 4b)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

DESCRIPTION = """\
Visual localisation on 7-Scenes with K reference images per scene (paper §5.1, Fig. 4b).

For every scene, the K most representative frames of the training sequences (TrainSplit.txt) are chosen by
K-means over DenseVLAD descriptors; each test frame (TestSplit.txt) is relocalized against its most similar
reference with --method, and scored against its ground-truth pose: precision and AUC at VCRE < 10 % (and 5 %)
of the image diagonal, at (5 cm, 5°) and (25 cm, 5°), median errors. Writes, under --out, one report per K
(report.json, table.txt, precision_ratio / vcre_cdf / scenes plots) and the K-vs-K comparison figures
(compare_precision_ratio, compare_vcre_cdf). Depth: the dataset's own maps use the suffix 'depth'.
"""

EPILOG = """\
examples:
  mapfree sevenscenes data/7scenes --method sift_pnp_depth --k 1,10 --out 7s-out
  mapfree sevenscenes data/7scenes --scenes chess,fire --method sift_emat_none --k 10 --mode triangulation
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sevenscenes",
        help="7-Scenes localisation with K reference images (paper Fig. 4b)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("root", type=Path, help="7-Scenes root (chess/, fire/, … each with seq-XX/ folders)")
    p.add_argument("--method", default="sift_pnp_depth", help="method name or YAML (default: sift_pnp_depth)")
    p.add_argument("--k", default="1,10", help="comma-separated numbers of references per scene (default: 1,10)")
    p.add_argument(
        "--mode",
        default="retrieval",
        choices=("retrieval", "triangulation"),
        help="'triangulation': the depth-free pose triangulation baseline (K >= 2; default: retrieval)",
    )
    p.add_argument("--scenes", help="comma-separated scene names (default: every scene under ROOT)")
    p.add_argument(
        "--mapping-stride",
        type=int,
        default=10,
        help="use every N-th training frame as a mapping candidate (default: 10)",
    )
    p.add_argument("--query-stride", type=int, default=10, help="localize every N-th test frame (default: 10)")
    p.add_argument(
        "--intrinsics",
        type=float,
        nargs=4,
        metavar=("FX", "FY", "CX", "CY"),
        help="colour camera intrinsics (default: 525 525 320 240)",
    )
    p.add_argument("--out", type=Path, default=Path("sevenscenes-out"), help="output folder (default: sevenscenes-out)")
    p.add_argument("--no-plots", action="store_true", help="reports only, no figures")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..data import FormatError

    try:
        ks = [int(k) for k in args.k.split(",") if k.strip()]
        if not ks or min(ks) < 1:
            raise ValueError(f"--k must list numbers >= 1, got {args.k!r}")
        if args.mapping_stride < 1 or args.query_stride < 1:
            raise ValueError("--mapping-stride and --query-stride must be >= 1")
        reports = evaluate_sevenscenes(
            args.root,
            args.method,
            ks,
            args.mode,
            args.scenes,
            args.mapping_stride,
            args.query_stride,
            args.intrinsics,
            progress=not args.no_progress,
        )
    except (FileNotFoundError, FormatError, KeyError, ValueError) as e:
        from . import fail

        return fail("sevenscenes", e)
    print(write_reports(reports, args.out, plots=not args.no_plots))
    if not any(r.estimated.any() for r in reports.values()):
        from . import EXIT_NOTHING

        print("mapfree sevenscenes: no frame got an estimate", file=sys.stderr)
        return EXIT_NOTHING
    return 0


def evaluate_sevenscenes(
    root, method, ks, mode="retrieval", scenes=None, mapping_stride=10, query_stride=10, intrinsics=None, progress=False
) -> dict:
    """{"K=k": Report} over the chosen scenes: K references per scene, every query localized and scored."""
    import numpy as np

    from ..benchmark.localization import localization_report
    from ..data.sevenscenes import COLOR_CAMERA, SevenScenes
    from ..relocalize import build_localizer
    from ..relocalize.references import localize_with_references

    ds = SevenScenes(root, tuple(intrinsics) if intrinsics is not None else COLOR_CAMERA)
    names = scenes.split(",") if isinstance(scenes, str) else (scenes or ds.scene_names())
    if not names:
        raise FileNotFoundError(f"{root}: no 7-Scenes scene folders (with seq-XX/) found")
    data = {n: (ds.scene(n).frames("train", mapping_stride), ds.scene(n).frames("test", query_stride)) for n in names}
    for n, (mapping, _) in data.items():
        if len(mapping) < max(ks):  # K is capped by the candidates: say so rather than print a K it never used
            print(
                f"mapfree sevenscenes: note: {n} has {len(mapping)} mapping frame(s) at --mapping-stride "
                f"{mapping_stride}, so K > {len(mapping)} uses {len(mapping)}; lower the stride for more",
                file=sys.stderr,
            )
    loc = build_localizer(method)
    reports = {}
    for k in ks:
        cols: dict[str, list] = {c: [] for c in ("scene", "frame", "qg", "tg", "qe", "te", "conf", "K", "W", "H")}
        for n, (mapping, queries) in data.items():
            _, ests = localize_with_references(method, mapping, queries, k, mode, progress=progress, localizer=loc)
            for f, e in zip(queries, ests):
                assert f.pose is not None  # SevenScenesScene.frames reads every frame's pose
                qg, tg = f.pose.qt()
                qe, te = e.pose.qt() if e.pose is not None else (np.full(4, np.nan), np.full(3, np.nan))
                Kf = f.intrinsics
                for c, v in zip(
                    cols,
                    (
                        n,
                        f.name,
                        qg,
                        tg,
                        qe,
                        te,
                        e.confidence if e.ok else np.nan,
                        [Kf.fx, Kf.fy, Kf.cx, Kf.cy],
                        Kf.width,
                        Kf.height,
                    ),
                ):
                    cols[c].append(v)
        reports[f"K={k}"] = localization_report(
            cols["scene"],
            cols["frame"],
            np.array(cols["qg"]).reshape(-1, 4),
            np.array(cols["tg"]).reshape(-1, 3),
            np.array(cols["qe"]).reshape(-1, 4),
            np.array(cols["te"]).reshape(-1, 3),
            np.array(cols["conf"]),
            np.array(cols["K"]).reshape(-1, 4),
            np.array(cols["W"]),
            np.array(cols["H"]),
            split="7scenes-test",
        )
    return reports


def write_reports(reports: dict, out: Path, plots: bool = True) -> str:
    """One folder per run (report.json, table.txt, plots), the comparison figures, and a summary table."""
    import io

    from rich.console import Console
    from rich.table import Table

    from ..benchmark import format_table, save_plots
    from ..benchmark.localization import save_comparison

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = Table(title="7-Scenes localisation")
    for c in (
        "run",
        "frames",
        "est. %",
        "med. t (m)",
        "med. R (°)",
        "med. VCRE (px)",
        "prec. VCRE<10%",
        "AUC VCRE<10%",
        "prec. VCRE<5%",
        "prec. 5cm,5°",
    ):
        summary.add_column(c, justify="left" if c == "run" else "right")
    for label, r in reports.items():
        d = out / label.replace("=", "")
        d.mkdir(exist_ok=True)
        (d / "report.json").write_text(r.to_json(frames=True))
        (d / "table.txt").write_text(format_table(r, per_scene=True))
        if plots:
            save_plots(r, d)
        summary.add_row(label, str(len(r.estimated)), *[_fmt(v) for v in _summary_values(r)])
    if plots and reports:
        save_comparison(reports, out)
    buffer = io.StringIO()
    Console(file=buffer, width=160, color_system=None).print(summary)
    text = buffer.getvalue()
    (out / "summary.txt").write_text(text)
    (out / "summary.json").write_text(json.dumps({k: r.to_dict()["metrics"] for k, r in reports.items()}, indent=2))
    return text


def _fmt(v) -> str:
    return "—" if v is None else f"{v:.3f}"


def _summary_values(r) -> list:
    """Estimates %, median t / R / VCRE, precision and AUC at VCRE < 10 %, precision at 5 %, at (5 cm, 5°)."""
    m = r.metrics
    return [
        None if m.estimated is None else 100 * m.estimated,
        m.median_trans,
        m.median_rot,
        m.median_vcre,
        m.vcre[0].precision,
        m.vcre[0].auc,
        m.vcre[1].precision,
        m.pose[0].precision,
    ]

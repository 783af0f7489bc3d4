"""Score every offline preset (matchers x solvers) on a split, with both confidences, plus paper-protocol's reference.

Matches are computed once per (matcher, pair) and shared by the three solvers; everything else is exactly
what ``mapfree run`` does (same ``Relocalizer`` code path, same presets). Prints markdown tables.

    python bench/score_presets.py /work/shared/data/realmini-dev --depth sensor [--all-frames] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

KEYS = [
    "AUC @ VCRE < 90px",
    "Precision @ VCRE < 90px",
    "AUC @ Pose Error < (25.0cm, 5deg)",
    "Precision @ Pose Error < (25.0cm, 5deg)",
    "Average Median Translation Error",
    "Average Median Rotation Error",
    "Average Median Reprojection Error",
    "Estimates for % of frames",
]
SHORT = ["VCRE AUC", "VCRE prec", "pose AUC", "pose prec", "med t (m)", "med R (°)", "med VCRE (px)", "estimated"]


def run_matcher(matcher: str, solvers: list[str], depth: str, scenes: list, all_frames: bool) -> tuple[dict, dict]:
    """{preset: {scene: [(frame, Estimate)]}} and timing sums for one matcher and several solvers."""
    from mapfree import matching
    from mapfree.methods import get, preset_name
    from mapfree.relocalize import Relocalizer, as_view
    from mapfree.relocalize.views import view_depth

    m = matching.create(matcher)
    locs = {}
    for s in solvers:
        method = get(preset_name(matcher, s, depth))
        locs[method.name] = Relocalizer(
            m, method.depth, method.solver, solver_opts=method.solver_opts, name=method.name
        )
    out: dict = {name: {} for name in locs}
    times = {"match": 0.0, "pairs": 0}
    first = next(iter(locs.values()))
    for scene in scenes:
        anchor = first.prepare(scene.reference)
        queries = scene.queries if all_frames else scene.scored_queries()
        for name in out:
            out[name][scene.name] = []
        for q in queries:
            t0 = time.perf_counter()
            view = as_view(q)
            matches = m.match(anchor.features, m.extract(view.image))
            times["match"] += time.perf_counter() - t0
            times["pairs"] += 1
            depth_q = view_depth(first.depth_source, view)
            for name, loc in locs.items():
                est = loc._solve(anchor, view, matches, depth_q)
                out[name][scene.name].append((q.name, est))
    return out, times


def to_submission(results: dict, confidence: str | None) -> dict:
    sub = {}
    for scene, rows in results.items():
        sub[scene] = [
            (f, e.pose, float(e.extras.get(confidence, e.confidence)) if confidence else e.confidence)
            for f, e in rows
            if e.pose is not None
        ]
    return sub


_TRUTH: dict = {}


def score(sub: dict, root, split: str, every: int) -> dict:
    """Benchmark metrics; ``every=1`` scores every query instead of every 5th."""
    from mapfree.benchmark import evaluate, load_scene_truth
    from mapfree.data import Dataset

    key = (str(root), split, every)
    if key not in _TRUTH:
        _TRUTH[key] = {
            s.name: load_scene_truth(s.path / "poses.txt", s.path / "intrinsics.txt", s.name, every=every)
            for s in Dataset(root).scenes(split)
        }
    # A scene without estimates is left out: its frames then count as failures, as they should.
    return evaluate({k: v for k, v in sub.items() if v}, root, split, truth=_TRUTH[key]).metrics.to_dict()


def table(rows: list[tuple[str, dict]]) -> str:
    lines = ["| method | " + " | ".join(SHORT) + " |", "|---|" + "---|" * len(SHORT)]
    for name, met in rows:
        vals = []
        for k in KEYS:
            v = met.get(k, float("nan"))
            vals.append(f"{v:.1f}" if "Reprojection" in k else f"{v:.3f}")
        lines.append(f"| {name} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root")
    ap.add_argument("--split", default="val")
    ap.add_argument("--depth", default="sensor")
    ap.add_argument("--matchers", default="sift,xfeat,xfeat-star,xfeat-lighterglue,aliked-lightglue,disk-lightglue")
    ap.add_argument("--solvers", default="emat,pnp,procrustes")
    ap.add_argument("--all-frames", action="store_true", help="relocalize and score every query, not every 5th")
    ap.add_argument(
        "--reference", action="store_true", help="also run the straightforward paper-protocol implementation"
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    import cv2
    import torch

    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    from mapfree.data import Dataset

    scenes = Dataset(args.root).scenes(args.split)
    every = 1 if args.all_frames else 5
    rows_inl, rows_score, timing = [], [], {}
    dump: dict = {}
    for matcher in args.matchers.split(","):
        t0 = time.perf_counter()
        res, times = run_matcher(matcher, args.solvers.split(","), args.depth, scenes, args.all_frames)
        timing[matcher] = {"seconds": time.perf_counter() - t0, **times}
        for name, results in res.items():
            a = score(to_submission(results, "confidence_inliers"), args.root, args.split, every)
            b = score(to_submission(results, "confidence_score"), args.root, args.split, every)
            rows_inl.append((name, a))
            rows_score.append((name, b))
            dump[name] = {"inliers": a, "score": b}
            print(
                f"{name}: VCRE AUC {a['AUC @ VCRE < 90px']:.3f} (inliers) {b['AUC @ VCRE < 90px']:.3f} (score)",
                file=sys.stderr,
                flush=True,
            )
    if args.reference:
        import reference_spec4

        sub, stats = reference_spec4.run(args.root, args.split, args.all_frames, args.depth)
        met = score(sub, args.root, args.split, every)
        rows_inl.insert(0, ("straightforward paper-protocol (sift, emat)", met))
        dump["reference_spec4"] = {"inliers": met, **stats}
    frames = "all queries" if args.all_frames else "scored queries (every 5th)"
    print(f"\n### {args.split}, depth `{args.depth}`, {frames}; confidence = inlier count (paper)\n")
    print(table(rows_inl))
    print("\n### same estimates, confidence = solver score (`confidence_score`)\n")
    print(table(rows_score))
    print("\nmatcher seconds:", json.dumps({k: round(v["seconds"], 1) for k, v in timing.items()}))
    if args.json:
        args.json.write_text(json.dumps({"metrics": dump, "timing": timing}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

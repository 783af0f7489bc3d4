"""Benchmark the scorer as whole processes: `mapfree evaluate --json` against the public evaluator's formulas.

Generates a test-shaped split (130 scenes, 15,000 evaluated frames: 75,000 ground-truth query lines per
file type; poses.txt all zeros as released, the true poses under a private ground-truth root) and a
submission with realistic errors, missing frames and tied confidences, in a temporary folder. Then, in one run:

1. checks that ``mapfree.benchmark.evaluate`` gives the numbers of the public evaluator's formulas
   (``mapfree.benchmark.naive``, a per-frame loop) to 1e-6, in both modes (default and ``--compat official``);
2. times whole processes, alternating them (A B A B ...) and taking medians: the public-evaluator reference
   (``naive.py`` loaded on its own, as a script would), ``mapfree evaluate --json``, and the floor
   (``python -c pass``, ``python -c "import numpy"``); prints the ratio (median of the per-pair ratios);
3. splits one ``mapfree evaluate`` into stages, timed inside a fresh process (median over the runs):
   imports, ZIP read (inflating the members alone), parse and checks, ground truth, metrics, output.

    python bench/bench_scoring.py [--scenes 130] [--frames 15000] [--repeat 5] [--keep DIR]
    python bench/bench_scoring.py --reference SUB.zip --dataset ROOT --split test --gt-root GT  # the yardstick

Wall and CPU (user + system of the child) are both printed: on a shared machine wall time also counts everyone
else's jobs; the ratio is taken pair by pair so that drifting load moves both sides.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy is imported where used: a stage run times its import
    import numpy as np

HERE = Path(__file__).resolve().parent
NAIVE = HERE.parent / "src" / "mapfree" / "benchmark" / "naive.py"


def _random_quats(rng: np.random.Generator, n: int, max_deg) -> np.ndarray:
    import numpy as np

    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    half = np.radians(rng.uniform(0, max_deg, n)) / 2
    return np.c_[np.cos(half), axis * np.sin(half)[:, None]]


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    import numpy as np

    w1, x1, y1, z1 = a.T
    w2, x2, y2, z2 = b.T
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 + y1 * w2 + z1 * x2 - x1 * z2,
            w1 * z2 + z1 * w2 + x1 * y2 - y1 * x2,
        ],
        axis=1,
    )


def make_split(
    root: Path,
    n_scenes: int,
    n_evaluated: int,
    seed: int = 0,
    all_queries: bool = False,
    split: str = "val",
    gt_root: Path | None = None,
) -> dict:
    """Write ``root/SPLIT/sNNNNN/{poses,intrinsics}.txt`` and return estimates for a submission. With ``gt_root``
    the true poses go to ``gt_root/SPLIT/sNNNNN/poses.txt`` and ``root``'s poses.txt holds zeros (test layout)."""
    import numpy as np

    from mapfree.geometry import Pose, quat_to_rotmat

    rng = np.random.default_rng(seed)
    per_scene = np.full(n_scenes, n_evaluated // n_scenes)
    per_scene[: n_evaluated - per_scene.sum()] += 1
    estimates = {}
    for s, m in enumerate(per_scene.tolist()):
        scene = f"s{s:05d}"
        d = root / split / scene
        d.mkdir(parents=True)
        n = 5 * m - 1  # queries; with the reference's shared key 0 the dict has 5m entries -> m evaluated
        names = ["seq0/frame_00000.jpg"] + [f"seq1/frame_{i:05d}.jpg" for i in range(n)]
        q = np.r_[[[1.0, 0, 0, 0]], _random_quats(rng, n, 40)]
        t = np.r_[[[0.0, 0, 0]], rng.normal(scale=1.5, size=(n, 3))]
        poses = "".join(
            f"{nm} {a:.9f} {b:.9f} {c:.9f} {e:.9f} {x:.6f} {y:.6f} {z:.6f}\n"
            for nm, (a, b, c, e), (x, y, z) in zip(names, q, t)
        )
        if gt_root is None:
            (d / "poses.txt").write_text(poses)
        else:
            (d / "poses.txt").write_text("".join(f"{nm} 0 0 0 0 0 0 0\n" for nm in names))
            (gt_root / split / scene).mkdir(parents=True)
            (gt_root / split / scene / "poses.txt").write_text(poses)
        fx = 590 + rng.normal(scale=3, size=n + 1)
        (d / "intrinsics.txt").write_text(
            "".join(f"{nm} {f:.6f} {f:.6f} 269.5 359.5 540 720\n" for nm, f in zip(names, fx))
        )
        # Estimates: errors spanning accepted poses to 180-degree flips, 3 % of frames missing.
        idx = np.arange(1, n + 1) if all_queries else 1 + np.arange(0, n, 5)
        k = len(idx)
        scale = rng.choice([0.02, 0.1, 0.5, 3.0], size=k, p=[0.3, 0.3, 0.3, 0.1])
        dq = _random_quats(rng, k, np.minimum(180.0, 40 * scale))
        q_est = _qmul(dq, q[idx])
        t_est = t[idx] + rng.normal(scale=scale[:, None], size=(k, 3))
        conf = rng.integers(0, 300, size=k).astype(float)  # many ties
        keep = rng.random(k) > 0.03
        R = quat_to_rotmat(q_est)
        estimates[scene] = [(names[i], Pose(R[j], t_est[j]), conf[j]) for j, i in enumerate(idx) if keep[j]]
    return estimates


def _load_naive():
    """``naive.py`` on its own, without importing the mapfree package (the public evaluator imports numpy only)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("naive_reference", NAIVE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def reference_main(a: argparse.Namespace) -> int:
    metrics, _ = _load_naive().evaluate_naive(a.reference, a.dataset, a.split, a.compat, a.gt_root)
    print(json.dumps(metrics, indent=2))
    return 0


STAGES = (
    "imports: numpy",
    "imports: mapfree and the standard library",
    "ZIP read (inflate)",
    "parse + checks",
    "ground truth",
    "metrics",
    "output",
)


def stages_main(a: argparse.Namespace) -> int:
    """One evaluation split into stages, in this fresh process; prints {stage: [wall, cpu]} as JSON."""
    clock = lambda: (time.perf_counter(), time.process_time())  # noqa: E731
    out: dict[str, list[float]] = {}
    last = clock()

    def lap(name: str) -> None:
        nonlocal last
        now = clock()
        out[name] = [now[0] - last[0], now[1] - last[1]]
        last = now

    import numpy  # noqa: F401

    lap("imports: numpy")
    import zipfile

    from mapfree.cli import build_parser

    build_parser("evaluate")  # as `mapfree evaluate` does
    from mapfree.benchmark import load_truth, read_submission, score

    lap("imports: mapfree and the standard library")
    with zipfile.ZipFile(a.stages) as zf:
        for info in zf.infolist():
            with zf.open(info) as f:
                while f.read(1 << 16):
                    pass
    lap("ZIP read (inflate)")
    truth = load_truth(a.dataset, a.split, a.gt_root)
    lap("ground truth")
    estimates, problems = read_submission(a.stages, {s: t.frame_names for s, t in truth.items()})
    lap("parse + checks")
    out["parse + checks"][0] -= out["ZIP read (inflate)"][0]  # read_submission inflates too
    out["parse + checks"][1] -= out["ZIP read (inflate)"][1]
    report = score(truth, estimates, problems, split=a.split)
    lap("metrics")
    with open(os.devnull, "w") as f:
        print(report.to_json(), file=f)
    lap("output")
    print(json.dumps(out))
    return 0


#: Child processes cache compiled bytecode (in a folder of their own), as an installed package has it: without
#: that (PYTHONDONTWRITEBYTECODE) every run would compile mapfree's modules again.
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def _run(cmd: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (user + system) of one whole process; its output is discarded."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, env=ENV)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=130)
    ap.add_argument("--frames", type=int, default=15000, help="evaluated frames in total")
    ap.add_argument("--repeat", type=int, default=5, help="runs of each whole process (medians)")
    ap.add_argument("--keep", type=Path, default=None, help="write the split here and keep it (default: a temp dir)")
    ap.add_argument("--reference", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--stages", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--dataset", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--split", default="test", help=argparse.SUPPRESS)
    ap.add_argument("--gt-root", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--compat", default="default", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.reference:
        return reference_main(args)
    if args.stages:
        return stages_main(args)

    from mapfree.benchmark import evaluate, write_submission

    tmp = None if args.keep else tempfile.mkdtemp(prefix="bench-scoring-")
    root = args.keep or Path(tmp)
    try:
        data, gt, sub = root / "data", root / "private_gt", root / "submission.zip"
        if not sub.is_file():
            shutil.rmtree(data, ignore_errors=True), shutil.rmtree(gt, ignore_errors=True)
            t0 = time.perf_counter()
            write_submission(sub, make_split(data, args.scenes, args.frames, split="test", gt_root=gt))
            print(f"generated {args.scenes} scenes in {time.perf_counter() - t0:.1f} s under {root}", file=sys.stderr)

        # 1. same numbers as the public evaluator's formulas, both modes
        naive = _load_naive()
        worst, n_eval = 0.0, 0
        for compat in ("default", "official"):
            report = evaluate(sub, data, "test", compat=compat, gt_root=gt)
            metrics, frames = naive.evaluate_naive(sub, data, "test", compat, gt)
            worst = max(worst, *(abs(report.metrics[k] - v) for k, v in metrics.items()))
            idx = {(s, f): i for i, (s, f) in enumerate(zip(report.scene, report.frame))}
            for key, errs in frames.items():
                i = idx[key]
                got = (report.trans_err[i], report.rot_err[i], report.vcre[i])
                worst = max(worst, *(abs(x - y) for x, y in zip(got, errs)))
            n_eval = len(report.estimated)
        ok = worst <= 1e-6

        # 2. whole processes, alternating
        ENV["PYTHONPYCACHEPREFIX"] = str(root / "pycache")
        py = sys.executable
        script = Path(py).parent / "mapfree"  # the console script, as users run it
        mapfree = [str(script)] if script.is_file() else [py, "-m", "mapfree"]
        split_args = [str(sub), "--dataset", str(data), "--split", "test", "--gt-root", str(gt)]
        commands = {
            "public-evaluator reference (naive.py, whole process)": [py, __file__, "--reference", *split_args],
            "mapfree evaluate --json": [*mapfree, "evaluate", *split_args, "--json"],
            "mapfree evaluate --json --compat official": [
                *mapfree,
                "evaluate",
                *split_args,
                "--json",
                "--compat",
                "official",
            ],
            "mapfree evaluate --help": [*mapfree, "evaluate", "--help"],
            'floor: python -c "import numpy"': [py, "-c", "import numpy"],
            "floor: python -c pass": [py, "-c", "pass"],
        }
        times: dict[str, list[tuple[float, float]]] = {k: [] for k in commands}
        stage_runs: list[dict] = []
        for k in commands:  # warm the file cache
            _run(commands[k])
        for _ in range(args.repeat):
            for k, cmd in commands.items():
                times[k].append(_run(cmd))
            out = subprocess.run(
                [py, __file__, "--stages", *split_args], capture_output=True, text=True, check=True, env=ENV
            )
            stage_runs.append(json.loads(out.stdout))
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)

    med = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for k, v in times.items()}
    ref_key, ours_key = list(commands)[:2]
    ratios = [r[0] / o[0] for r, o in zip(times[ref_key], times[ours_key])]
    cpu_ratios = [r[1] / o[1] for r, o in zip(times[ref_key], times[ours_key])]
    ratio, cpu_ratio = statistics.median(ratios), statistics.median(cpu_ratios)

    w = 58
    print(
        f"\n{args.scenes} scenes, {n_eval} evaluated frames, test split with private ground truth; "
        f"whole processes, median of {args.repeat}"
    )
    print(f"{'':<{w}}  {'wall (s)':>9}  {'CPU (s)':>8}")
    for k, (wall, cpu) in med.items():
        print(f"{k:<{w}}  {wall:>9.3f}  {cpu:>8.3f}")
    print(f"{'ratio reference / mapfree evaluate (median of pairs)':<{w}}  {ratio:>8.1f}x  {cpu_ratio:>7.1f}x")
    floor = med['floor: python -c "import numpy"']
    print(
        f"{'best ratio possible with numpy (reference / the floor)':<{w}}  {med[ref_key][0] / floor[0]:>8.1f}x  "
        f"{med[ref_key][1] / floor[1]:>7.1f}x"
    )
    print(
        f"{'max |difference| from the reference, both modes':<{w}}  {worst:>9.1e}  "
        f"{'identical to 1e-6' if ok else 'DIFFERENT'}"
    )

    print(f"\nmapfree evaluate by stage (inside a fresh process, median of {args.repeat}; start-up from the floor)")
    start = med["floor: python -c pass"]
    rows = [("interpreter start-up (python -c pass)", *start)]
    rows += [
        (s, statistics.median(r[s][0] for r in stage_runs), statistics.median(r[s][1] for r in stage_runs))
        for s in STAGES
    ]
    for name, wall, cpu in rows:
        print(f"{name:<{w}}  {wall:>9.3f}  {cpu:>8.3f}")
    print(f"{'sum of stages':<{w}}  {sum(r[1] for r in rows):>9.3f}  {sum(r[2] for r in rows):>8.3f}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""MicKey's speed through ``mapfree run``: the published architecture (DINOv2 ViT-L/14 and the four heads) with
fill-rule weights in the published file layout (no download; accuracy needs the real weights), against a light
baseline preset on the same pairs in the same call.

    python bench/bench_mickey.py [ROOT] [--scenes s00000] [--presets mickey,xfeat_pnp_sensor] [--threads N] [--loop]

Each preset runs in a fresh process (``mapfree run ROOT --method PRESET --scenes ...``): its wall time (model
loading and each scene's reference included), CPU time and peak memory, and from its journal the median
per-pair network time (``match``: the query's pass through the network and the pair's scores) and solver time.
``--loop`` adds the public code's way of running pairs (both images through the network per pair, batch 1), on
the same pairs: on a GPU, the comparison for ``mapfree run``'s batches and cached references.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchpaths import DEFAULT_ROOT  # noqa: E402  (also puts src/ on the path)


def run_preset(root: Path, preset: str, scenes: str, weights: Path, out: Path, threads: int) -> dict:
    """One ``mapfree run`` in a fresh process: wall/CPU seconds, peak memory, per-pair median timings."""
    zip_path = out / f"{preset}.zip"
    env = {
        **os.environ,
        "MAPFREE_WEIGHTS_DIR": str(weights),
        "MAPFREE_OFFLINE": "1",
        **{v: str(threads) for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")},
    }
    cmd = [
        sys.executable,
        "-m",
        "mapfree",
        "run",
        str(root),
        "--method",
        preset,
        "--scenes",
        scenes,
        "-o",
        str(zip_path),
        "--overwrite",
        "--no-progress",
    ]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    log = proc.stdout.read() if proc.stdout else ""
    if os.waitstatus_to_exitcode(status) not in (0, 3):
        raise SystemExit(f"{preset}: mapfree run failed:\n{log}")
    journal = zip_path.with_name(zip_path.stem + ".journal.jsonl")
    frames = [r for r in map(json.loads, journal.read_text().splitlines()) if r.get("kind") == "frame"]

    def med(key: str) -> float:
        vals = [r["timings"][key] for r in frames if key in r["timings"]]
        return statistics.median(vals) if vals else float("nan")

    return {
        "preset": preset,
        "pairs": len(frames),
        "estimates": sum(r["ok"] for r in frames),
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_gib": usage.ru_maxrss / 2**20,
        "pairs_per_s": len(frames) / wall,
        "match_s": med("match"),
        "solve_s": med("solve"),
    }


def solver_seconds(threads: int, n: int = 51 * 38, repeats: int = 2) -> float:
    """Median seconds of MicKey's solver (published settings) on one pair of ``n`` keypoints each: its cost
    depends on the sizes, not on the weights. Fill-rule weights match every cell with the same cell of the
    other image, so ``mapfree run`` answers such pairs with the identity pose without calling a solver."""
    import torch

    from mapfree.solvers.mickey import probabilistic_procrustes

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    scores = torch.rand(1, n, n, generator=g) ** 8
    X0 = torch.rand(1, n, 3, generator=g) * 4 + torch.tensor([0.0, 0.0, 2.0])
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        probabilistic_procrustes(scores, X0, X0.flip(1), generator=g)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def loop_pairs_per_s(root: Path, scenes: str, weights: Path, threads: int) -> tuple[int, float]:
    """The public code's loop, run with our port: per pair, both images through the network (batch 1, nothing
    kept between pairs), the pair scored and solved. (pairs, pairs/s) on the same pairs as ``mapfree run``."""
    import torch

    from mapfree.data import Dataset
    from mapfree.mickey.engine import shared_engine
    from mapfree.solvers.mickey import lift, probabilistic_procrustes

    os.environ["MAPFREE_WEIGHTS_DIR"] = str(weights)
    torch.set_num_threads(threads)
    engine = shared_engine()
    sync = torch.cuda.synchronize if engine.device.type == "cuda" else (lambda: None)
    ds = Dataset(root)
    n, t0 = 0, time.perf_counter()
    for name in scenes.split(","):
        scene = ds.scene("val", name)
        ref = scene.reference
        for query in scene.scored_queries():  # what `mapfree run` runs by default
            a, b = (engine.extract([v.image()], batch_size=1)[0] for v in (ref, query))
            final = engine.scores(a, [b])[0]
            X0 = lift(a.xy_original().float(), a.keypoints.depth[0], ref.intrinsics.K)
            X1 = lift(b.xy_original().float(), b.keypoints.depth[0], query.intrinsics.K)
            probabilistic_procrustes(
                final[None], X0[None], X1[None], generator=torch.Generator(device=final.device).manual_seed(0)
            )
            sync()
            n += 1
    return n, n / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", type=Path, default=DEFAULT_ROOT)
    ap.add_argument("--scenes", default="s00000")
    ap.add_argument(
        "--presets",
        default="mickey,xfeat_pnp_sensor",
        help="the first is timed, the others are baselines in the same call",
    )
    ap.add_argument("--threads", type=int, default=2, help="torch/BLAS threads of each run")
    ap.add_argument(
        "--size",
        choices=("full", "tiny"),
        default="full",
        help="'tiny': a two-block DINOv2, to rehearse the script quickly",
    )
    ap.add_argument(
        "--loop",
        action="store_true",
        help="also time the public code's loop (both images per pair through the network, batch 1) on the same pairs",
    )
    ap.add_argument("--json", type=Path, help="also write the rows here")
    args = ap.parse_args(argv)
    if args.root is None:
        ap.error("no dataset root given and realmini-dev not found")
    import torch

    from mapfree_dev.standins.mickey import write_standin

    rows = []
    with tempfile.TemporaryDirectory() as d:
        weights = write_standin(Path(d) / "weights", args.size, dtype=torch.float16)
        for preset in args.presets.split(","):
            rows.append(run_preset(args.root, preset, args.scenes, weights, Path(d), args.threads))
            print(f"{preset}: done in {rows[-1]['wall_s']:.1f} s", file=sys.stderr, flush=True)
        loop = loop_pairs_per_s(args.root, args.scenes, weights, args.threads) if args.loop else None
    device = "cuda" if torch.cuda.is_available() else f"cpu ({os.cpu_count()} cores, {args.threads} threads)"
    vit = "ViT-L/14" if args.size == "full" else "tiny DINOv2"
    print(f"device: {device}; scenes {args.scenes} of {args.root}; MicKey {vit} with fill-rule weights")
    print(
        "| preset | pairs | estimates | wall s (whole process) | CPU s | pairs/s | per pair: network s | "
        "solver s | peak memory |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['preset']} | {r['pairs']} | {r['estimates']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
            f"{r['pairs_per_s']:.3f} | {r['match_s']:.2f} | {r['solve_s']:.2f} | {r['peak_gib']:.1f} GiB |"
        )
    if loop is not None:
        print(
            f"\npublic code's loop (our port; both images per pair, batch 1, solver on every pair): {loop[0]} "
            f"pairs, {loop[1]:.3f} pairs/s"
        )
    solve = solver_seconds(args.threads)
    print(f"\nMicKey's solver alone (published settings, 1938 x 1938 candidates): {solve:.2f} s per pair")
    mk = next((r for r in rows if r["preset"] == "mickey"), None)
    if mk is not None and mk["solve_s"] < 0.1 * solve:  # the run's pairs skipped it (zero parallax)
        per_pair = mk["wall_s"] / mk["pairs"] + solve
        print(f"mickey with its solver on every pair (as with real weights): ~{1 / per_pair:.3f} pairs/s")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "solver_s": solve, "loop": loop}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

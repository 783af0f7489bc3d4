"""`mapfree run` frames/s: the local process pool vs a Ray cluster of 1, 2, 3 nodes on this machine, side by side.

Writes a synthetic val split (SCENES scenes of QUERIES queries), then for N = 1, 2, 3 starts a Ray cluster of N
nodes with CPUS_PER_NODE CPUs each (``ray.cluster_utils.Cluster``: a head and N - 1 worker nodes, all on this
machine) and times, back to back, two whole `mapfree run --all-frames` processes with the same total workers
W = N x CPUS_PER_NODE: the local pool (``--workers W``) and Ray (``--ray ADDRESS``, one worker per CPU), each
REPEAT times in alternating order, the best of each counting; one thread per worker everywhere. Every run must
write the same ZIP, byte for byte. On one machine the cores, not the nodes, are the limit, so Ray's
frames/s should match the pool's: the ratio column is what the engine costs. Then the per-task overhead: the
round trip of an empty chunk to a warm worker, and its share of a run (chunks per run x overhead / run time).

    PYTHONPATH=src .venv/bin/python bench/bench_ray.py [--scenes 6] [--queries 100] [--size 320x240]
                                                      [--nodes 1,2,3] [--cpus-per-node 1] [--repeat 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # every node on the loopback address
os.environ.setdefault("RAY_AUTH_MODE", "disabled")  # a throw-away cluster on this machine

from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from mapfree.data.synth import SynthOptions, generate  # noqa: E402

MB = 1024 * 1024


def _timed_run(root: Path, out: Path, method: str, extra: list[str]) -> tuple[float, dict]:
    """Seconds of one whole `mapfree run` process (Python start, workers' start and the frames), and its summary."""
    cmd = [sys.executable, "-m", "mapfree", "run", str(root), "--method", method, "-o", str(out), "--all-frames",
           "--no-progress", "--json", *extra]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": _src()})
    return time.perf_counter() - t0, json.loads(done.stdout)


def _src() -> str:
    return os.pathsep.join([str(Path(__file__).resolve().parents[1] / "src"), os.environ.get("PYTHONPATH", "")])


def _task_overhead_ms(address: str, method: str, scene: Path, n: int = 100) -> float:
    """Mean round trip (ms) of an empty chunk to a warm worker: dispatch, the stream's end, the driver's wait."""
    import ray

    from mapfree.methods import get
    from mapfree.relocalize.distributed import FrameWorker

    ray.init(address=address, log_to_driver=False, configure_logging=False)
    try:
        worker = ray.remote(FrameWorker).options(num_cpus=1).remote(get(method).to_dict(), 1)
        ray.get(worker.setup.remote(str(scene.parents[1]), scene.parent.name, [str(scene)]))
        list(worker.run.options(num_returns="streaming").remote(str(scene), [], None, False))  # the scene opened
        t0 = time.perf_counter()
        for _ in range(n):
            for ref in worker.run.options(num_returns="streaming").remote(str(scene), [], None, False):
                ray.get(ref)
        return (time.perf_counter() - t0) / n * 1000
    finally:
        ray.shutdown()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--size", default="320x240", help="image size WxH")
    ap.add_argument("--nodes", default="1,2,3", help="cluster sizes, comma-separated")
    ap.add_argument("--cpus-per-node", type=int, default=1)
    ap.add_argument("--method", default="sift_pnp_sensor")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each kind per cluster size (the best counts)")
    args = ap.parse_args()
    # One thread per worker everywhere (Ray's workers and the pool's take one each; the pool's single-process
    # case would otherwise run OpenMP across every core and lose to its own spinning on a loaded machine).
    os.environ["OMP_NUM_THREADS"] = "1"
    from ray.cluster_utils import Cluster

    w, h = (int(v) for v in args.size.split("x"))
    frames = args.scenes * args.queries
    rows, overhead = [], None
    with tempfile.TemporaryDirectory(prefix="bench-ray") as tmp:
        root = Path(tmp) / "data"
        generate(root, "val", args.scenes, args.queries, options=SynthOptions(width=w, height=h, write_mono=False),
                 progress=False)
        reference: bytes | None = None
        tasks = 0
        for n in (int(v) for v in args.nodes.split(",")):
            workers = n * args.cpus_per_node
            node = {"num_cpus": args.cpus_per_node, "object_store_memory": 80 * MB}
            cluster = Cluster(initialize_head=True, head_node_args={**node, "include_dashboard": False})
            try:
                for _ in range(n - 1):
                    cluster.add_node(**node)
                cluster.wait_for_nodes()
                local_out, ray_out = Path(tmp) / f"local{n}.zip", Path(tmp) / f"ray{n}.zip"
                runs = {"local": (local_out, ["--workers", str(workers)]), "ray": (ray_out, ["--ray", cluster.address])}
                best: dict[str, float] = {}
                for r in range(args.repeat):  # interleaved, alternating order; the best of each
                    for kind in ("local", "ray") if r % 2 == 0 else ("ray", "local"):
                        out, extra = runs[kind]
                        seconds, summary = _timed_run(root, out, args.method, ["--overwrite", *extra])
                        best[kind] = min(best.get(kind, seconds), seconds)
                        tasks = summary["cluster"]["tasks"] if kind == "ray" else tasks
                t_local, t_ray = best["local"], best["ray"]
                if overhead is None:
                    overhead = _task_overhead_ms(cluster.address, args.method, root / "val" / "s00000")
            finally:
                cluster.shutdown()
            for out in (local_out, ray_out):
                reference = reference or out.read_bytes()
                assert out.read_bytes() == reference, f"{out.name} differs from the first run's ZIP"
            rows.append((workers, frames / t_local, n, frames / t_ray, t_local / t_ray, tasks, t_ray))

    table = Table(title=f"mapfree run --all-frames, {args.method}, {frames} frames ({args.scenes} scenes x "
                        f"{args.queries}, {args.size}); whole processes, best of {args.repeat}; {os.cpu_count()}-core CPU")
    for col in ("workers", "local pool frames/s", "Ray nodes", "Ray frames/s", "Ray / local", "Ray tasks",
                "overhead share"):
        table.add_column(col, justify="right")
    for workers, f_local, n, f_ray, ratio, tasks, t_ray in rows:
        share = tasks * overhead / 1000 / t_ray
        table.add_row(str(workers), f"{f_local:.1f}", str(n), f"{f_ray:.1f}", f"{ratio:.2f}", str(tasks),
                      f"{100 * share:.2f} %")
    Console().print(table)
    print(f"Ray per-task overhead: {overhead:.1f} ms (round trip of an empty chunk to a warm worker); every run "
          f"wrote the same ZIP")


if __name__ == "__main__":
    main()

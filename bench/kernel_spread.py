"""The float32 spread of the exactness tests across CPU kernel paths, against their tolerances.

The fixture tests (MASt3R/DUSt3R, MicKey, the official RPR releases) compare our port with outputs the public code
recorded on some machine. Another CPU takes other kernels (AVX-512, AVX2 or the portable ones), another thread
count sums in another order, and PyTorch's fused attention rounds differently from the explicit softmax the public
code computes: none of that is a port error, and a tolerance must cover it on any x86-64 CPU. This script runs
the tests themselves under each path (``ATEN_CPU_CAPABILITY`` × 1 or 2 threads × fused or explicit attention),
records every error they check (``MAPFREE_FIXTURE_ERRORS``), and prints per kind of output the largest error of
each path beside its tolerance (tests/fixture_tolerance.py). A capability the CPU lacks (AVX-512 here) is skipped and
said so: torch would take it on trust and die of an illegal instruction.

    PYTHONPATH=src .venv/bin/python bench/kernel_spread.py            # tiny models, ~8 runs of 1-2 minutes
    PYTHONPATH=src .venv/bin/python bench/kernel_spread.py --full     # the full-size networks too (slow)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from fixture_tolerance import TOLERANCES  # noqa: E402

TESTS = ["tests/test_mast3r.py", "tests/test_mickey.py", "tests/test_rpr_official.py"]
SELECT = "reproduce or solver_draws or public_pose"


Worst = dict[str, tuple[float, float]]


def _supported(capability: str) -> bool:
    """Whether this CPU can run ``capability``'s kernels (torch takes ``avx512`` on trust: SIGILL without it)."""
    flags = Path("/proc/cpuinfo").read_text().split()
    need = {"default": [], "avx2": ["avx2", "fma"], "avx512": ["avx512f", "avx512bw", "avx512vl", "avx512dq"]}
    return all(f in flags for f in need[capability])


def run_path(capability: str, threads: int, attention: str, full: bool) -> Worst:
    """Run the fixture tests on one kernel path; per kind of output, the largest error and the largest mean error
    over one array."""
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "errors.jsonl"
        env = {
            **os.environ,
            "ATEN_CPU_CAPABILITY": capability,
            "MAPFREE_TEST_TORCH_THREADS": str(threads),
            "MAPFREE_FIXTURE_ERRORS": str(log),
            "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "bench"), os.environ.get("PYTHONPATH", "")]),
        }
        cmd = [sys.executable, "-m", "pytest", *TESTS, "-q", "-p", "no:cacheprovider", "-k", SELECT]
        cmd += [] if full else ["-m", "not slow"]
        if attention == "explicit":
            cmd += ["-p", "explicit_attention"]
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        if proc.returncode != 0 or not log.exists():  # the tests only record in this mode: a failure is a crash
            sys.exit(
                f"the tests failed on {capability}/{threads}/{attention}:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}"
            )
        worst: dict[str, tuple[float, float]] = defaultdict(lambda: (0.0, 0.0))
        for line in log.read_text().splitlines():
            rec = json.loads(line)
            top, mean = worst[rec["kind"]]
            worst[rec["kind"]] = (max(top, rec["max"]), max(mean, rec["mean"]))
    return dict(worst)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--full", action="store_true", help="also the full-size networks (tests marked slow)")
    ap.add_argument("--capabilities", default="default,avx2,avx512")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--json", type=Path, help="write the table's numbers here too")
    args = ap.parse_args()
    columns: list[tuple[str, Worst]] = []
    for cap in args.capabilities.split(","):
        if not _supported(cap):
            print(f"skip {cap}: this CPU lacks it", file=sys.stderr)
            continue
        for threads in map(int, args.threads.split(",")):
            for attention in ("fused", "explicit"):
                label = f"{cap}/{threads}t/{attention}"
                columns.append((label, run_path(cap, threads, attention, args.full)))
                print(f"ran {label}: {json.dumps(columns[-1][1])}", file=sys.stderr, flush=True)
    kinds = [k for k in TOLERANCES if any(k in w for _, w in columns)]
    print("largest error of each path (max over the arrays of a kind; for kinds with a mean bound: max / mean)")
    print(f"{'kind':<22} {'tolerance':>15} {'margin':>7}  " + "  ".join(c for c, _ in columns))
    for kind in kinds:
        tol = TOLERANCES[kind]
        vals = [w.get(kind, (float("nan"), float("nan"))) for _, w in columns]
        top = max(v[0] for v in vals if v[0] == v[0])
        margin = tol.max / top
        if tol.mean is not None:
            margin = min(margin, tol.mean / max(v[1] for v in vals if v[1] == v[1]))
        cells = "  ".join(
            f"{(f'{v[0]:.1e}/{v[1]:.1e}' if tol.mean is not None else f'{v[0]:.1e}'):>{len(c)}}"
            for (c, _), v in zip(columns, vals)
        )
        bound = f"{tol.max:.0e}/{tol.mean:.0e}" if tol.mean is not None else f"{tol.max:.0e}"
        print(f"{kind:<22} {bound:>15} {margin:>6.1f}x  {cells}")
    if args.json:
        args.json.write_text(json.dumps({c: w for c, w in columns}, indent=1))


if __name__ == "__main__":
    main()

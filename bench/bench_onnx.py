"""MASt3R on the CPU: our PyTorch port against its exported graphs in onnxruntime, files in to matches out.

    python bench/bench_onnx.py [ROOT] [--size 512] [--pairs 3] [--threads 2] [--model vitl|tiny]

The published ViT-L architecture with fill-rule weights in the published file layout (written once to a cache
folder; no download, so the matches are not meaningful, their cost is) is exported by ``mapfree export`` for the
photos' shape at ``--size``. Then each backend runs in a fresh process on the same never-seen realmini-dev pairs
(each scene's reference against its seq1 frames, in order; the reference's encoding is cached as in ``mapfree
run``): per pair, the two files read, encoded (the query; the reference once per scene), decoded and matched.
Printed: the median per-pair wall and CPU time (warm-up pair excluded), the process's peak memory (loading
included), and the matches both backends agree on.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from benchpaths import DEFAULT_ROOT  # noqa: E402  (also puts src/ on the path)

SCENES = ("s00001", "s00002")  # the tests use s00000; s00003 has photos of another size (640x480)


def pairs(root: Path, n: int) -> list[tuple[Path, Path]]:
    """``n`` pairs (reference, seq1 frame) per scene, every 5th frame from frame 5 (never seen by the tests)."""
    out = []
    for s in SCENES:
        d = root / "val" / s
        out += [(d / "seq0" / "frame_00000.jpg", d / "seq1" / f"frame_{i:05d}.jpg") for i in range(5, 5 + 5 * n, 5)]
    return out


def worker(args: argparse.Namespace) -> None:
    """One backend in this process: JSON of per-pair times, peak memory and the matches."""
    import numpy as np
    import torch

    from mapfree.data import read_image
    from mapfree.matching.mast3r import Mast3rMatcher

    torch.set_num_threads(args.threads)
    opts = {"backend": "onnxruntime", "onnx": args.onnx} if args.worker == "onnxruntime" else {"weights": args.weights}
    t0 = time.perf_counter()
    m = Mast3rMatcher(long_side=args.size, device="cpu", **opts)
    load = time.perf_counter() - t0
    refs: dict[Path, object] = {}
    rows, matches = [], []
    for ref, query in pairs(Path(args.root), args.pairs):
        w0, c0 = time.perf_counter(), time.process_time()
        if ref not in refs:
            refs[ref] = m.extract(read_image(ref))
        res = m.match(refs[ref], m.extract(read_image(query)))
        rows.append((time.perf_counter() - w0, time.process_time() - c0))
        matches.append(np.c_[res.kpts0, res.kpts1].round(3).tolist())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"load": load, "rows": rows, "peak_mib": peak, "matches": matches}))


def run_worker(backend: str, args: argparse.Namespace, weights: Path, onnx_path: Path) -> dict:
    env = {**os.environ, **{v: str(args.threads) for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}}
    cmd = [sys.executable, __file__, str(args.root), "--worker", backend, "--size", str(args.size)]
    cmd += [
        "--pairs",
        str(args.pairs),
        "--threads",
        str(args.threads),
        "--weights",
        str(weights),
        "--onnx",
        str(onnx_path),
    ]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"{backend}: failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("root", nargs="?", type=Path, default=DEFAULT_ROOT)
    ap.add_argument("--size", type=int, default=512, help="network input long side (published: 512)")
    ap.add_argument("--pairs", type=int, default=3, help="pairs per scene (2 scenes)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--model", choices=("vitl", "tiny"), default="vitl", help="published ViT-L, or the tests' tiny")
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "mapfree-bench" / "onnx")
    ap.add_argument("--worker", choices=("torch", "onnxruntime"), help=argparse.SUPPRESS)
    ap.add_argument("--weights", help=argparse.SUPPRESS)
    ap.add_argument("--onnx", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        return worker(args)
    import numpy as np
    import PIL.Image

    from mapfree.mast3r.checkpoint import PUBLISHED
    from mapfree.mast3r.export import export_matcher

    folder = args.cache / args.model
    folder.mkdir(parents=True, exist_ok=True)
    weights = folder / f"{PUBLISHED['mast3r'].stem}.pth"
    if not weights.is_file():
        print(f"writing fill-rule weights to {weights}", file=sys.stderr)
        if args.model == "vitl":
            import torch

            from mapfree_dev.standins.mast3r import write_published_standin

            write_published_standin(folder, "mast3r", torch.float16)  # half the file; computed in float32
        else:
            from mapfree.mast3r.config import config_from_kwargs, parse_constructor
            from mapfree_dev.standins.mast3r import save_pth, synthetic_state_dict

            spec = json.loads((args.root.parent.parent / "fixtures/mast3r/mast3r.json").read_text())
            expr = spec["models"]["mast3r-tiny"]["expr"]
            save_pth(weights, expr, synthetic_state_dict(config_from_kwargs(*parse_constructor(expr))))
    with PIL.Image.open(pairs(args.root, 1)[0][1]) as im:
        photo = im.size
    onnx_path = folder / f"mast3r-{args.size}-{photo[0]}x{photo[1]}.onnx"
    if not onnx_path.is_file():
        t0 = time.perf_counter()
        export_matcher("mast3r", onnx_path, args.size, photo, weights, progress=lambda s: print(s, file=sys.stderr))
        print(f"exported in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    res = {b: run_worker(b, args, weights, onnx_path) for b in ("torch", "onnxruntime")}

    def med(b: str, i: int) -> float:
        return statistics.median(r[i] for r in res[b]["rows"][1:])  # the first pair warms up

    same = [
        len({tuple(x) for x in a} & {tuple(x) for x in b}) / max(len(a), len(b), 1)
        for a, b in zip(res["torch"]["matches"], res["onnxruntime"]["matches"])
    ]
    n = len(res["torch"]["rows"])
    print(
        f"MASt3R {args.model}, {args.size} long side ({photo[0]}x{photo[1]} photos), {args.threads} threads, "
        f"{n} pairs of {', '.join(SCENES)} (median of the last {n - 1})"
    )
    print("| backend | per pair wall s | per pair CPU s | peak memory MiB | load s |")
    print("|---|---|---|---|---|")
    for b in ("torch", "onnxruntime"):
        print(f"| {b} | {med(b, 0):.2f} | {med(b, 1):.2f} | {res[b]['peak_mib']:.0f} | {res[b]['load']:.1f} |")
    print(
        f"onnxruntime speed-up (wall): {med('torch', 0) / med('onnxruntime', 0):.2f}x; "
        f"identical matches: min {min(same):.1%}, mean {float(np.mean(same)):.1%}"
    )


if __name__ == "__main__":
    main()

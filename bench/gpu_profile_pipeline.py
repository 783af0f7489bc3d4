"""Where ``mapfree run``'s time goes on a GPU, for presets that miss their pairs/s target:

    MAPFREE_OFFLINE=1 python bench/gpu_profile_pipeline.py ROOT --out DIR [--presets a,b] [--batches 16,64]

Per preset, in one process warmed up on mirrored images (as ``bench_pipeline.py``): the first pass over the
never-seen pairs under the torch profiler (CPU and CUDA operators) and cProfile (the calling thread: extraction,
matching and the hand-over to the solver threads), then the same pairs again at each batch size of ``--batches``
(seen pairs: a comparison between batch sizes, not a figure). Everything lands in DIR/profile.md.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def profile_preset(
    root: Path, split: str, name: str, batches: list[int], rows: int = 18, max_pairs: int | None = None
) -> str:
    import torch
    from torch.profiler import ProfilerActivity, profile

    from bench_pipeline import _scenes_with_depth, _warm_up
    from mapfree.methods import get
    from mapfree.relocalize import frames_to_run, run_split, scenes

    gpu = torch.cuda.is_available()
    sync = torch.cuda.synchronize if gpu else (lambda: None)

    loc = scenes.built_localizer(get(name))
    _warm_up(loc, root, split, 4)
    scenes = _scenes_with_depth(root, split)
    out = [f"## {name}", ""]
    with tempfile.TemporaryDirectory() as tmp:

        def once(batch: int) -> tuple[int, float]:
            sync()
            t0 = time.perf_counter()
            res = run_split(
                root,
                split,
                name,
                Path(tmp) / "sub.zip",
                all_frames=True,
                scenes=scenes,
                progress=False,
                overwrite=True,
                batch_size=batch,
                select=lambda s: frames_to_run(s, True)[:max_pairs],
            )
            sync()
            return res.computed, time.perf_counter() - t0

        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if gpu else [])
        prof, cprof = profile(activities=activities), cProfile.Profile()
        with prof:
            cprof.enable()
            n, wall = once(batches[0])
            cprof.disable()
        out += [
            f"first pass, batch {batches[0]}, under both profilers: {n} pairs in {wall:.2f} s "
            f"({n / wall:.1f} pairs/s with the profilers' overhead)",
            "",
        ]
        for b in batches:
            n, wall = once(b)
            out.append(f"- seen pairs, batch {b}: {n / wall:.1f} pairs/s ({1000 * wall / n:.1f} ms per pair)")
        avg = prof.key_averages()
        cuda_total = sum(e.self_device_time_total for e in avg) / 1000
        out += [
            "",
            f"CUDA kernel time in all: {cuda_total:.0f} ms over {n} pairs ({cuda_total / n:.1f} ms per pair)",
            "",
            "### operators by their own CPU time",
            "",
            "```",
            avg.table(sort_by="self_cpu_time_total", row_limit=rows),
            "```",
            "",
            "### operators by their own CUDA time",
            "",
            "```",
            avg.table(sort_by="self_cuda_time_total" if gpu else "cpu_time_total", row_limit=rows // 2),
            "```",
            "",
        ]
        buf = io.StringIO()
        pstats.Stats(cprof, stream=buf).sort_stats("cumulative").print_stats(rows + 12)
        out += ["### the calling thread (cProfile, cumulative)", "", "```", buf.getvalue().strip(), "```", ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    from bench_pipeline import DEFAULT_ROOT, resized_split

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", type=Path, default=DEFAULT_ROOT)
    ap.add_argument("--out", type=Path, default=Path("gpu-profile"))
    ap.add_argument("--split", default="val")
    ap.add_argument("--presets", default="aliked-lightglue_emat_sensor,xfeat-lighterglue_emat_sensor")
    ap.add_argument("--batches", default="16,64", help="batch sizes of the seen-pairs passes (the first: profiled)")
    ap.add_argument("--size", default="540x720")
    ap.add_argument("--quick", action="store_true", help="a rehearsal on any device: 1 pair per scene, batch 2")
    args = ap.parse_args(argv)
    import torch

    if not torch.cuda.is_available() and not args.quick:
        print("no GPU here: this profile is of the GPU path (--quick rehearses it on the CPU)")
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    device = torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu (a rehearsal)"
    lines = [f"# Pipeline profile: {device}, torch {torch.__version__}", ""]
    with tempfile.TemporaryDirectory() as tmp:
        w, h = (int(v) for v in args.size.split("x"))
        root = resized_split(args.root, args.split, (w // 2, h // 2) if args.quick else (w, h), Path(tmp))
        batches = [2] if args.quick else [int(b) for b in args.batches.split(",")]
        for name in args.presets.split(","):
            lines.append(profile_preset(root, args.split, name, batches, max_pairs=1 if args.quick else None))
            (args.out / "profile.md").write_text("\n".join(lines) + "\n")
            print(lines[-1], flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

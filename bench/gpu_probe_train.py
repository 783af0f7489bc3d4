"""The RPR-training GPU figures of issue 9 (point 4) in one call, for a session with a GPU (one H100 expected):

    MAPFREE_OFFLINE=1 python bench/gpu_probe_train.py [--root ROOT] [--out DIR] [--large 64] [--quick]

1. ``bench/bench_train.py`` for ``rot6d_trans`` (the paper's R(6D)+t) at 360×270, at the paper's batch (10) and
   at a large batch: step rows before → after, the loader, the loop with GPU utilisation;
2. the fused warping against the explicit volume on the GPU at 360×270 (fp32 outputs and gradients, bf16 vs fp32),
   where the attention kernels differ from the CPU's;
3. a torch profile of five steps before and after at the large batch: the operators that take the CUDA time;
4. the step rows again with a torch.compile row, at both batches (last: compiling takes minutes).
Everything printed also lands in DIR/probe_train.md, rewritten after each section; paste the tables into the
the training throughput section of docs/regression.md.
``--quick`` is a rehearsal of every step on any device (CPU included): batches 2 and 3 at 128×176, one timed
step, no compile row; its numbers are not figures.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gpu_probe import stream

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
QUICK_SIZE = "128x176"  # --quick: network input W x H (a rehearsal of the code paths, not the paper's size)


def equivalence(batch: int = 2, hw: tuple[int, int] = (90, 68)) -> str:
    """Largest differences of the fused warping from the explicit volume on this device, 32-d features of
    ``hw`` (default 1/4 of 360×270; what tests/test_rpr_fast_train.py checks on CPU at small sizes)."""
    import copy

    import torch

    from mapfree.rpr.aggregator import CorrelationAggregator

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    ref = CorrelationAggregator(32, fused=False).to(device)
    fast = copy.deepcopy(ref)
    fast.fused = True
    g = torch.Generator(device=device).manual_seed(0)
    f0, f1 = (torch.randn(batch, 32, *hw, generator=g, device=device) for _ in range(2))
    weight = torch.randn(batch, ref.out_channels, *hw, generator=g, device=device)

    def run(agg, amp=False):
        a, b = f0.clone().requires_grad_(), f1.clone().requires_grad_()
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            out = agg(a, b)
        (out.float() * weight).sum().backward()
        return out.detach().float(), a.grad, b.grad

    want, got, half = run(ref), run(fast), run(fast, amp=True)
    rel = lambda x, y: float((x - y).abs().max() / y.abs().max())  # noqa: E731
    peak = lambda x, y: float(((x[:, -1] - y[:, -1]).abs() / y[:, -1]).max())  # noqa: E731
    return (
        f"fp32 fused vs explicit: output {rel(got[0], want[0]):.1e}, grad f0 {rel(got[1], want[1]):.1e}, "
        f"grad f1 {rel(got[2], want[2]):.1e} (relative to the largest value; CPU: ~1e-5 / 1e-4); "
        f"peak probability {peak(got[0], want[0]):.1e} relative; "
        f"bf16 fused vs fp32 explicit: features/positions {float((half[0] - want[0])[:, :-1].abs().max()):.3f} "
        f"absolute, peak {peak(half[0], want[0]):.3f} relative"
    )


def profile(batch: int, steps: int = 5, size: tuple[int, int] | None = None) -> str:
    """Operators by their own CUDA time over ``steps`` training steps, before and after (CPU time without a GPU),
    at the config's input size or ``size`` (W, H)."""
    import torch
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    from bench_train import Trainer, _random_batch, _size, _sync
    from mapfree.rpr.config import load_config
    from mapfree.rpr.train import resolve_config

    cfg = load_config(resolve_config("rot6d_trans"))
    if size:
        cfg.data.image_size = size
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    data = {k: v.to(device) for k, v in _random_batch(_size(cfg), batch).items()}
    out = []
    for name, kw in (
        ("before", dict(fused=False, amp=False, channels_last=False)),
        ("after", dict(fused=True, amp=True, channels_last=True)),
    ):
        try:
            tr = Trainer(cfg, device, **kw)
            tr.step(data)
            _sync(device)
            with torch_profile(activities=activities) as prof:
                for _ in range(steps):
                    tr.step(data)
                _sync(device)
            table = prof.key_averages().table(sort_by=f"self_{device.type}_time_total", row_limit=15)
        except torch.cuda.OutOfMemoryError:
            table = "out of GPU memory"
        out.append(f"### {name}, batch {batch}, {steps} steps\n\n```\n{table}\n```\n")
        tr = None
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    from bench_pipeline import DEFAULT_ROOT

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT)
    ap.add_argument("--out", type=Path, default=Path("gpu-probe-train"))
    ap.add_argument("--large", type=int, default=64, help="the large batch")
    ap.add_argument("--workers", type=int, default=12)
    ap.add_argument("--quick", action="store_true", help="rehearse every step on any device, in a few minutes")
    ap.add_argument(
        "--profile-only",
        action="store_true",
        help="only the fused-warp check and the CUDA profile (a call that already has the step rows)",
    )
    ap.add_argument(
        "--no-compile",
        dest="compile",
        action="store_false",
        help="skip the torch.compile rows (compiling takes minutes of a short device lease)",
    )
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    import torch

    gpu = torch.cuda.is_available()
    if not gpu and not args.quick:
        print(
            "no GPU here: this probe only fills in GPU figures (bench/bench_train.py runs on CPU; --quick "
            "rehearses this probe on the CPU)"
        )
        return 1
    device = torch.cuda.get_device_name() if gpu else "no GPU (cpu)"
    lines = [
        f"# RPR training probe: {device}, torch {torch.__version__}"
        + (" (--quick: a rehearsal, not figures)" if args.quick else ""),
        "",
    ]
    have_images = args.root is not None and Path(args.root).is_dir()
    batches = (2, 3) if args.quick else (10, args.large)
    steps, warmup, epochs, per_epoch = ("1", "1", "1", 2) if args.quick else ("10", "3", "3", 20)

    def save() -> None:  # after every section: a call cut at its time limit keeps what was measured
        (args.out / "probe_train.md").write_text("\n".join(lines) + "\n")

    def bench(batch: int, parts: str, extra: list[str], timeout: float) -> None:
        cmd = [
            sys.executable,
            str(HERE / "bench_train.py"),
            "--config",
            "rot6d_trans",
            "--device",
            "cuda" if gpu else "cpu",
            "--batch",
            str(batch),
            "--steps",
            steps,
            "--warmup",
            warmup,
            "--workers",
            str(min(args.workers, 2) if args.quick else args.workers),
            "--epochs",
            epochs,
            "--loop-pairs",
            str(per_epoch * batch),
            "--parts",
            parts,
            *extra,
        ]
        cmd += ["--root", str(args.root)] if have_images and parts != "step" else []
        lines.extend(
            [
                f"## batch {batch}" + (", torch.compile" if "--compile" in extra else ""),
                "",
                "`python " + " ".join(cmd[1:]) + "`",
                "",
            ]
        )
        print("\n".join(lines[-4:]), flush=True)
        lines.extend([stream(cmd, timeout=timeout), ""])
        save()

    # The compile rows come last: compiling takes minutes and must not cost the other rows if the call runs out.
    for batch in () if args.profile_only else batches:
        bench(batch, "step,loader,loop" if have_images else "step", ["--size", QUICK_SIZE] if args.quick else [], 240)
    lines += [
        "## fused warping vs the explicit volume on this device",
        "",
        equivalence(1, (44, 32)) if args.quick else equivalence(),
        "",
    ]
    print("\n".join(lines[-4:]), flush=True)
    quick_size = tuple(int(v) for v in QUICK_SIZE.split("x"))
    lines += ["## where the CUDA time goes", "", profile(2, 1, quick_size) if args.quick else profile(args.large)]
    print(lines[-1], flush=True)
    save()
    if not args.quick and args.compile and not args.profile_only:
        for batch in batches:
            bench(batch, "step", ["--compile"], 150)
    return 0


if __name__ == "__main__":
    sys.exit(main())

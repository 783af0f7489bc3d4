"""RPR training throughput before and after issue 9's changes, in one run (pairs/s, GPU utilisation).

Three parts, each "before" (the code as it was: explicit correlation volume, fp32, JPEG decoded every time,
float32 batches, workers restarted every epoch) against "after" (``soft_warp`` on attention kernels,
bf16 autocast where the device has it, channels-last, images decoded once into ``data.cache_dir``, uint8
batches, persistent workers, pinned memory):

1. ``step``: the training step alone on one batch held on the device, one row per change, plus where a step's
   time goes (forward, backward, optimizer);
2. ``loader``: the data pipeline alone on real images (ROOT's val pairs);
3. ``loop``: the two together, as training runs them, with the GPU's utilisation while it runs.

    python bench/bench_train.py                                  # rot6d_trans (the paper's R(6D)+t), 360×270, batch 10
    python bench/bench_train.py --batch 64 --device cuda --workers 12
    python bench/bench_train.py --config R6D_t_cpu_synth --batch 8 --parts step
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_pipeline import DEFAULT_ROOT  # noqa: E402
from gpu_util import GpuUtilisation  # noqa: E402
from mapfree.data import Dataset  # noqa: E402
from mapfree.rpr.config import load_config  # noqa: E402
from mapfree.rpr.data import PairDataset, as_float_input, resized_image, resolve_size, val_pairs  # noqa: E402
from mapfree.rpr.losses import PoseLoss  # noqa: E402
from mapfree.rpr.model import RPRNet  # noqa: E402
from mapfree.rpr.train import resolve_config  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def _size(cfg) -> tuple[int, int]:
    """(W, H) of the network input for Map-free's portrait frames (the config's image_size if it has one)."""
    return resolve_size((cfg.data.short_side, cfg.data.long_side), cfg.data)


class Trainer:
    """One network, loss and Adam with a given recipe; ``step(batch)`` is one training step."""

    def __init__(
        self,
        cfg,
        device: torch.device,
        fused: bool,
        amp: bool,
        channels_last: bool,
        compile_net: bool = False,
        cached: bool = False,
    ):
        torch.manual_seed(0)
        torch.backends.cudnn.benchmark = fused  # after: fixed input size, convolution kernels chosen once
        self.device, self.amp, self.cl, self.cached = device, amp, channels_last, cached
        self._feats: tuple[torch.Tensor, torch.Tensor] | None = None
        self.net = RPRNet(cfg.model, cfg.data.image_size).to(device)
        if hasattr(self.net.aggregator, "fused"):
            self.net.aggregator.fused = fused
        if channels_last:
            self.net = self.net.to(memory_format=torch.channels_last)
        if compile_net:  # in place: parameter names stay those of the checkpoints
            self.net.encoder.compile()
            self.net.head.compile()
        self.loss = PoseLoss(cfg.loss).to(device)
        params = [p for p in self.net.parameters() if p.requires_grad]
        self.opt = torch.optim.Adam(params, lr=1e-4, fused=device.type == "cuda")
        self.dtype = torch.bfloat16 if device.type == "cpu" or torch.cuda.is_bf16_supported() else torch.float16
        self.net.train()

    def inputs(self, batch: dict) -> tuple[torch.Tensor, ...]:
        out = []
        for k in ("img0", "img1"):
            x = as_float_input(batch[k].to(self.device, non_blocking=True))
            out.append(x.contiguous(memory_format=torch.channels_last) if self.cl else x)
        return (*out, batch["R"].to(self.device, non_blocking=True), batch["t"].to(self.device, non_blocking=True))

    def step(self, batch: dict, phases: dict[str, float] | None = None) -> None:
        img0, img1, R, t = self.inputs(batch)
        t0 = time.perf_counter()
        with torch.autocast(device_type=self.device.type, dtype=self.dtype, enabled=self.amp):
            if self.cached:  # train.cache_features: a frozen encoder's features, computed once per image
                if self._feats is None:
                    with torch.no_grad():
                        self._feats = self.net.encoder(img0), self.net.encoder(img1)
                out = self.net.from_features(*self._feats)
            else:
                out = self.net(img0, img1)
            loss = self.loss(out, R, t)["loss"]
        if phases is not None:
            _sync(self.device)
            t1 = time.perf_counter()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        if phases is not None:
            _sync(self.device)
            t2 = time.perf_counter()
        self.opt.step()
        if phases is not None:
            _sync(self.device)
            t3 = time.perf_counter()
            for k, v in (("forward", t1 - t0), ("backward", t2 - t1), ("optimizer", t3 - t2)):
                phases[k] = phases.get(k, 0.0) + v


def _random_batch(size: tuple[int, int], batch: int) -> dict[str, torch.Tensor]:
    w, h = size
    g = torch.Generator().manual_seed(0)
    return {
        "img0": torch.randint(0, 256, (batch, 3, h, w), generator=g, dtype=torch.uint8),
        "img1": torch.randint(0, 256, (batch, 3, h, w), generator=g, dtype=torch.uint8),
        "R": torch.eye(3).expand(batch, 3, 3).contiguous(),
        "t": torch.randn(batch, 3, generator=g),
    }


def bench_step(cfg, device, batch: int, steps: int, warmup: int, rows) -> list[dict]:
    """Pairs/s of the training step alone for each recipe (same batch, already on the device)."""
    data = {k: v.to(device) for k, v in _random_batch(_size(cfg), batch).items()}
    out = []
    for name, kw in rows:
        try:
            out.append(_step_row(name, kw, cfg, device, data, batch, steps, warmup))
        except Exception as e:  # out of GPU memory (the explicit volume at a large batch), or no compiler
            if not (isinstance(e, torch.cuda.OutOfMemoryError) or kw.get("compile_net")):
                raise
            why = "out of GPU memory" if isinstance(e, torch.cuda.OutOfMemoryError) else f"failed: {e!r:.80}"
            out.append(
                {
                    "name": f"{name} ({why})",
                    "pairs_s": float("nan"),
                    "util": None,
                    "mem_gib": None,
                    "forward": float("nan"),
                    "backward": float("nan"),
                    "optimizer": float("nan"),
                }
            )
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return out


def _step_row(name: str, kw: dict, cfg, device, data, batch: int, steps: int, warmup: int) -> dict:
    tr = Trainer(cfg, device, **kw)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    for _ in range(warmup):
        tr.step(data)
    _sync(device)
    t0 = time.perf_counter()
    with GpuUtilisation() as util:
        for _ in range(steps):
            tr.step(data)
        _sync(device)
    wall = time.perf_counter() - t0
    phases: dict[str, float] = {}
    tr.step(data, phases)
    mem = torch.cuda.max_memory_allocated() / 2**30 if device.type == "cuda" else None
    return {"name": name, "pairs_s": batch * steps / wall, "util": util.mean, "mem_gib": mem, **phases}


def _pairs(root: Path, n: int) -> list:
    pairs = val_pairs(Dataset(root).scenes("val"), every_query=1)
    if not pairs:
        raise SystemExit(f"{root}: no val pairs to load")
    return (pairs * (n // len(pairs) + 1))[:n]


def _loader(pairs, size, batch: int, workers: int, after: bool, cache_dir: str | None) -> DataLoader:
    """The training loader before (float32, decode every time, plain workers) or after the change."""
    ds = PairDataset(pairs, size, cache_dir=cache_dir if after else None, uint8=after)
    return DataLoader(
        ds,
        batch_size=batch,
        shuffle=True,
        num_workers=workers,
        drop_last=True,
        persistent_workers=after and workers > 0,
        pin_memory=after and torch.cuda.is_available(),
        prefetch_factor=4 if after and workers > 0 else None,
    )


def _fill_cache(pairs, size, cache_dir: str) -> float:
    """Decode and resize every frame once (what the first epoch does); seconds taken."""
    t0 = time.perf_counter()
    scenes: dict = {}
    ds = PairDataset(pairs, size, scenes=scenes)
    for scene, name in {(p.scene, n) for p in pairs for n in (p.name0, p.name1)}:
        resized_image(ds.scene(scene).frame(name), size, cache_dir=cache_dir)
    return time.perf_counter() - t0


def bench_loader(pairs, size, batch: int, workers: int, epochs: int, cache_dir: str) -> list[dict]:
    """Pairs/s of the loader alone over ``epochs`` passes (workers restart each epoch unless persistent)."""
    out = []
    for after in (False, True):
        loader = _loader(pairs, size, batch, workers, after, cache_dir)
        t0, n = time.perf_counter(), 0
        for _ in range(epochs):
            for b in loader:
                n += len(b["img0"])
        out.append({"name": "after" if after else "before", "pairs_s": n / (time.perf_counter() - t0)})
        del loader
    return out


def bench_loop(cfg, device, pairs, size, batch: int, workers: int, epochs: int, cache_dir: str, rows) -> list[dict]:
    """Pairs/s and GPU utilisation of loader + step together, before and after."""
    out = []
    for (name, kw), after in zip(rows, (False, True)):
        try:
            out.append(_loop_row(name, kw, after, cfg, device, pairs, size, batch, workers, epochs, cache_dir))
        except torch.cuda.OutOfMemoryError:
            out.append({"name": f"{name} (out of GPU memory)", "pairs_s": float("nan"), "util": None})
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return out


def _loop_row(name, kw, after, cfg, device, pairs, size, batch, workers, epochs, cache_dir) -> dict:
    tr = Trainer(cfg, device, **kw)
    loader = _loader(pairs, size, batch, workers, after, cache_dir)
    tr.step(next(iter(loader)))  # warm-up (kernels, autotuning), not timed
    _sync(device)
    t0, n = time.perf_counter(), 0
    with GpuUtilisation() as util:
        for _ in range(epochs):
            for b in loader:
                tr.step(b)
                n += len(b["img0"])
        _sync(device)
    return {"name": name, "pairs_s": n / (time.perf_counter() - t0), "util": util.mean}


def _fmt(v, spec: str = ".1f") -> str:
    return "–" if v is None else format(v, spec)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="rot6d_trans", help="config name in configs/rpr or a YAML path")
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="images for the loader (its val pairs)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--batch", type=int, default=10)
    ap.add_argument("--steps", type=int, default=3, help="timed steps per step row")
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--workers", type=int, default=min(8, os.cpu_count() or 1))
    ap.add_argument("--loop-pairs", type=int, default=0, help="pairs per loop epoch (0: 4 batches)")
    ap.add_argument("--epochs", type=int, default=2, help="epochs of the loader and loop parts")
    ap.add_argument("--parts", default="step,loader,loop")
    ap.add_argument("--compile", action="store_true", help="add a row with torch.compile'd encoder and head")
    ap.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: leave as is)")
    ap.add_argument("--size", help="network input WxH instead of the config's (small: a quick rehearsal)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = load_config(resolve_config(args.config))
    if args.size:
        cfg.data.image_size = tuple(int(v) for v in args.size.lower().split("x"))
    device = torch.device(args.device)
    size = _size(cfg)
    parts = set(args.parts.split(","))
    amp = "bf16" if device.type == "cpu" or torch.cuda.is_bf16_supported() else "fp16"
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {torch.get_num_threads()} threads"
    print(
        f"RPR training throughput — {cfg.name} ({args.config}), input {size[0]}×{size[1]}, batch {args.batch}, "
        f"{gpu}, torch {torch.__version__}, {args.workers} loader workers"
    )
    before = ("before: reference warp, fp32", dict(fused=False, amp=False, channels_last=False))
    after = (f"after: fused warp, {amp}, channels-last", dict(fused=True, amp=True, channels_last=True))
    if "step" in parts:
        rows = [
            before,
            ("fused warp, fp32", dict(fused=True, amp=False, channels_last=False)),
            ("fused warp, fp32, channels-last", dict(fused=True, amp=False, channels_last=True)),
            (f"fused warp, {amp}", dict(fused=True, amp=True, channels_last=False)),
            after,
        ]
        if args.compile:
            rows.append((after[0] + ", compiled", dict(after[1], compile_net=True)))
        if RPRNet(cfg.model, cfg.data.image_size).frozen_encoder:  # train.cache_features: encoder once per image
            rows.append((after[0] + ", cached encoder features", dict(after[1], cached=True)))
        res = bench_step(cfg, device, args.batch, args.steps, args.warmup, rows)
        base = res[0]["pairs_s"]
        print(f"\n## step (one batch on the device, {args.steps} timed steps)\n")
        print("| recipe | pairs/s | vs before | GPU util % | peak GiB | forward ms | backward ms | optimizer ms |")
        print("|---|---|---|---|---|---|---|---|")
        for r in res:
            print(
                f"| {r['name']} | {r['pairs_s']:.2f} | {r['pairs_s'] / base:.2f}× | {_fmt(r['util'])} | "
                f"{_fmt(r['mem_gib'], '.2f')} | {1000 * r['forward']:.0f} | {1000 * r['backward']:.0f} | "
                f"{1000 * r['optimizer']:.0f} |"
            )
    if parts & {"loader", "loop"}:
        pairs = _pairs(args.root, args.loop_pairs or 4 * args.batch)
        with tempfile.TemporaryDirectory(prefix="rpr-cache-") as cache_dir:
            filled = _fill_cache(pairs, size, cache_dir)
            print(
                f"\nimage cache: {len({(p.scene, n) for p in pairs for n in (p.name0, p.name1)})} frames decoded and "
                f"resized once in {1000 * filled:.0f} ms (after rows read them back; before rows decode every time)"
            )
            if "loader" in parts:
                res = bench_loader(pairs, size, args.batch, args.workers, args.epochs, cache_dir)
                print(f"\n## loader alone ({len(pairs)} pairs × {args.epochs} epochs)\n")
                print("| loader | pairs/s | vs before |\n|---|---|---|")
                for r in res:
                    print(f"| {r['name']} | {r['pairs_s']:.1f} | {r['pairs_s'] / res[0]['pairs_s']:.2f}× |")
            if "loop" in parts:
                res = bench_loop(
                    cfg, device, pairs, size, args.batch, args.workers, args.epochs, cache_dir, [before, after]
                )
                print(f"\n## loop: loader + step ({len(pairs)} pairs × {args.epochs} epochs)\n")
                print("| recipe | pairs/s | vs before | GPU util % |\n|---|---|---|---|")
                for r in res:
                    print(
                        f"| {r['name']} | {r['pairs_s']:.2f} | {r['pairs_s'] / res[0]['pairs_s']:.2f}× | "
                        f"{_fmt(r['util'])} |"
                    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

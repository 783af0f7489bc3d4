"""RPR training and inference throughput (pairs/s): mixed precision and channels-last vs plain fp32.

Every row runs the same network on the same random batch in this process; ratios are against the plain
fp32 training loop measured here. CPU by default (bf16 autocast); on a GPU run with --device cuda.

    python bench/bench_train.py                      # CPU-synthetic config (frozen XFeat, 192×256), batch 8
    python bench/bench_train.py --config rot6d_trans # the paper's network at 360×270
    python bench/bench_train.py --device cuda --batch 10 --config rot6d_trans
"""

from __future__ import annotations

import argparse
import time

import torch

from mapfree.regression.config import load_config
from mapfree.regression.losses import PoseLoss
from mapfree.regression.model import RPRNet
from mapfree.regression.train import resolve_config


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def _batch(cfg, batch: int, device: torch.device, channels_last: bool) -> dict[str, torch.Tensor]:
    w, h = cfg.data.short_side, cfg.data.long_side  # portrait, as the Map-free images
    g = torch.Generator().manual_seed(0)
    b = {"img0": torch.rand(batch, 3, h, w, generator=g), "img1": torch.rand(batch, 3, h, w, generator=g),
         "R": torch.eye(3).expand(batch, 3, 3).contiguous(), "t": torch.randn(batch, 3, generator=g)}
    b = {k: v.to(device) for k, v in b.items()}
    if channels_last:
        b["img0"] = b["img0"].contiguous(memory_format=torch.channels_last)
        b["img1"] = b["img1"].contiguous(memory_format=torch.channels_last)
    return b


def measure(cfg, device: torch.device, batch: int, steps: int, warmup: int, amp: bool, channels_last: bool,
            train: bool, cached: bool = False) -> float:
    """Pairs per second of ``steps`` timed iterations after ``warmup`` untimed ones.

    ``cached``: a frozen encoder's features computed once beforehand (train.cache_features), so the step
    runs only what trains: aggregator, head and MLP (the steady state once every image has been seen).
    """
    torch.manual_seed(0)
    net = RPRNet(cfg.model, cfg.data.image_size).to(device)
    if channels_last:
        net = net.to(memory_format=torch.channels_last)
    loss_fn = PoseLoss(cfg.loss).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    net.train(train)
    data = _batch(cfg, batch, device, channels_last)
    dtype = torch.bfloat16 if device.type == "cpu" or torch.cuda.is_bf16_supported() else torch.float16
    if cached:
        with torch.no_grad():
            f0, f1 = net.encoder(data["img0"]), net.encoder(data["img1"])

    def step() -> None:
        with torch.autocast(device_type=device.type, dtype=dtype, enabled=amp):
            if train:
                out = net.from_features(f0, f1) if cached else net(data["img0"], data["img1"])
                loss = loss_fn(out, data["R"], data["t"])["loss"]
        if train:
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            opt.step()
        else:
            with torch.inference_mode(), torch.autocast(device_type=device.type, dtype=dtype, enabled=amp):
                net(data["img0"], data["img1"])

    for _ in range(warmup):
        step()
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    _sync(device)
    return batch * steps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="R6D_t_cpu_synth", help="config name in configs/rpr or a YAML path")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: leave as is)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = load_config(resolve_config(args.config))
    device = torch.device(args.device)
    w, h = cfg.data.short_side, cfg.data.long_side
    amp_name = "bf16" if device.type == "cpu" or torch.cuda.is_bf16_supported() else "fp16"
    print(f"RPR throughput — {cfg.name}, input {w}×{h}, batch {args.batch}, device {device}"
          f" ({torch.get_num_threads()} threads), {args.steps} timed steps")
    rows = [("train", "fp32 (plain loop, baseline)", False, False, True),
            ("train", f"{amp_name} autocast", True, False, True),
            ("train", "fp32 channels-last", False, True, True),
            ("train", f"{amp_name} autocast + channels-last", True, True, True),
            ("infer", "fp32", False, False, False),
            ("infer", "fp32 channels-last", False, True, False),
            ("infer", f"{amp_name} autocast", True, False, False),
            ("infer", f"{amp_name} autocast + channels-last", True, True, False)]
    results = []
    for kind, name, amp, cl, train in rows:
        results.append((kind, name, measure(cfg, device, args.batch, args.steps, args.warmup, amp, cl, train)))
    if RPRNet(cfg.model, cfg.data.image_size).frozen_encoder:  # the frozen XFeat encoder: also the cached-feature training step
        results.insert(4, ("train", "fp32 cached encoder features", measure(
            cfg, device, args.batch, args.steps, args.warmup, False, False, True, cached=True)))
    base = {k: next(r for kk, _, r in results if kk == k) for k in ("train", "infer")}
    print(f"{'mode':<6} {'variant':<36} {'pairs/s':>9} {'vs fp32':>8}")
    for kind, name, r in results:
        print(f"{kind:<6} {name:<36} {r:>9.2f} {r / base[kind]:>7.2f}x")


if __name__ == "__main__":
    main()

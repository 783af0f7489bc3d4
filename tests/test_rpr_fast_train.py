"""RPR training throughput (issue 9): the attention-kernel warping equals the explicit correlation volume
(outputs and gradients) without ever holding it; decoded-once images, uint8 batches and per-epoch resampling
inside one dataset give the same data as the plain path."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("pytorch_lightning")

from torch.utils._python_dispatch import TorchDispatchMode

from mapfree.data import Dataset
from mapfree.rpr import aggregator as agg_mod
from mapfree.rpr.aggregator import CorrelationAggregator
from mapfree.rpr.data import (
    EpochSampler,
    PairDataset,
    RPRDataModule,
    TrainPairs,
    as_float_input,
    load_pair_image,
    resized_image,
    val_pairs,
)

sys.path.insert(0, str(Path(__file__).parent))
from test_rpr_train import make_tiny_root, tiny_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")

VARIANTS = {
    "warp": {},
    "qkv": {"qkv": True},
    "cosine+own grid": {"temperature": 0.05, "own_position": True},
    "no max score": {"max_score": False},
    "no position": {"position": False},
}


def _both(kw: dict, dim: int = 16) -> tuple[CorrelationAggregator, CorrelationAggregator]:
    torch.manual_seed(0)
    ref = CorrelationAggregator(dim, fused=False, **kw)
    fast = copy.deepcopy(ref)
    fast.fused = True
    return ref, fast


def _run(agg, f0, f1, weight):
    """Output and gradients of a weighted sum of the aggregated volume."""
    f0, f1 = f0.clone().requires_grad_(), f1.clone().requires_grad_()
    out = agg(f0, f1)
    (out.float() * weight).sum().backward()
    grads = [p.grad for p in agg.parameters()]
    return out.detach().float(), f0.grad, f1.grad, grads


@pytest.mark.parametrize("name", list(VARIANTS))
def test_fused_warping_equals_the_correlation_volume(name):
    ref, fast = _both(VARIANTS[name])
    g = torch.Generator().manual_seed(1)
    f0, f1 = (torch.randn(2, 16, 11, 9, generator=g) for _ in range(2))  # peaked and flat rows alike
    weight = torch.randn(2, ref.out_channels, 11, 9, generator=g)
    want, got = _run(ref, f0, f1, weight), _run(fast, f0, f1, weight)
    assert got[0].shape == want[0].shape and torch.isfinite(got[0]).all()
    torch.testing.assert_close(got[0], want[0], rtol=1e-4, atol=1e-5)
    for a, b in zip(got[1:3] + tuple(got[3]), want[1:3] + tuple(want[3])):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * float(b.abs().max()))
    if VARIANTS[name].get("max_score", True):  # the peak channel is a probability, and really varies
        peak = got[0][:, -1]
        assert peak.min() > 0 and peak.max() <= 1 + 1e-6 and peak.std() > 0.05


def test_fused_warping_under_bf16_autocast_is_as_close_to_float32_as_the_reference():
    ref, fast = _both({})
    g = torch.Generator().manual_seed(2)
    f0, f1 = (torch.randn(2, 16, 12, 10, generator=g) for _ in range(2))
    truth = ref(f0, f1)
    errors = {}
    for name, agg in (("ref", ref), ("fast", fast)):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            got = agg(f0, f1).float()
        err = (got - truth).abs()
        # features and positions (absolute), the peak probability (relative: small values count as much)
        errors[name] = (float(err[:, :-1].max()), float((err[:, -1] / truth[:, -1]).max()))
    assert errors["fast"][0] < 0.05 and errors["fast"][1] < 0.06, errors
    assert errors["fast"][0] <= 1.5 * errors["ref"][0] and errors["fast"][1] <= 1.5 * errors["ref"][1], errors


class _LargestTensor(TorchDispatchMode):
    """Records the largest tensor any operator returns (forward and backward)."""

    def __init__(self):
        super().__init__()
        self.numel = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in out if isinstance(out, (tuple, list)) else (out,):
            if isinstance(t, torch.Tensor):
                self.numel = max(self.numel, t.numel())
        return out


def test_fused_warping_never_holds_the_volume_and_chunks_its_argmax(monkeypatch):
    ref, fast = _both({})
    g = torch.Generator().manual_seed(3)
    f0, f1 = (torch.randn(2, 16, 24, 20, generator=g) for _ in range(2))
    weight = torch.randn(2, ref.out_channels, 24, 20, generator=g)
    volume = 2 * (24 * 20) ** 2  # feature-sized tensors are 2 * 480 * 40 at most
    want = _run(ref, f0, f1, weight)
    monkeypatch.setattr(agg_mod, "_ARGMAX_CHUNK", volume // 8)  # the argmax pass in 8 row chunks
    with _LargestTensor() as probe:
        got = _run(fast, f0, f1, weight)
    torch.testing.assert_close(got[0], want[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(got[1], want[1], rtol=1e-4, atol=1e-4 * float(want[1].abs().max()))
    assert probe.numel <= volume // 8
    with _LargestTensor() as probe:
        _run(ref, f0, f1, weight)
    assert probe.numel >= volume  # the reference does build it: the probe sees it


def test_decode_once_cache_gives_the_same_pixels_and_survives_a_torn_file(realmini, tmp_path, caplog):
    scene = Dataset(realmini).scenes("val")[0]
    frames = [scene.reference, *scene.queries[:2]]
    size = (270, 360)
    direct = [load_pair_image(f, size)[0] for f in frames]
    decoded = {}
    for f, want in zip(frames, direct):  # first use decodes and writes, second reads back
        first = decoded[str(Path(f.name).with_suffix(""))] = resized_image(f, size, cache_dir=tmp_path)
        again = resized_image(f, size, cache_dir=tmp_path)
        assert again.dtype == np.uint8 and np.array_equal(first, again)
        assert np.array_equal(as_float_input(torch.from_numpy(again)).numpy(), want)  # bit-identical input
    stored = sorted(tmp_path.rglob("*.npy"))
    assert len(stored) == 3 and all(p.parts[-4:-2] == ("val", scene.name) for p in stored)
    assert stored[0].stat().st_size < 300_000
    stored[0].write_bytes(stored[0].read_bytes()[:1000])  # a torn write from a killed run
    torn = f"{stored[0].parent.name}/{stored[0].stem}"
    frame = next(f for f in frames if str(Path(f.name).with_suffix("")) == torn)
    with caplog.at_level("WARNING"):
        img = resized_image(frame, size, cache_dir=tmp_path)
    assert "unreadable cached image" in caplog.text
    assert np.array_equal(img, decoded[torn])
    assert np.load(stored[0]).shape == (360, 270, 3)  # rewritten whole


def test_uint8_batches_give_the_network_the_same_input(realmini, tmp_path):
    pairs = val_pairs(Dataset(realmini).scenes("val")[:1])[:3]
    plain = PairDataset(pairs, (270, 360))
    lean = PairDataset(pairs, (270, 360), cache_dir=str(tmp_path), uint8=True)
    for i in range(len(pairs)):
        a, b = plain[i], lean[i]
        assert b["img0"].dtype == torch.uint8 and a["img0"].dtype == torch.float32
        for k in ("img0", "img1"):
            assert torch.equal(as_float_input(b[k]), a[k])
        for k in ("R", "t", "K0", "K1"):
            assert torch.equal(a[k], b[k])


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory) -> Path:
    return make_tiny_root(tmp_path_factory.mktemp("rpr_fast"))


def test_one_dataset_with_persistent_workers_resamples_every_epoch(tiny_root):
    dm = RPRDataModule(tiny_config(tiny_root, num_workers=1, batch_size=2).data)
    dm.setup("fit")
    epoch = {"now": 0}
    dm._epoch = lambda: epoch["now"]  # what the trainer's current epoch would say
    loader = dm.train_dataloader()
    assert loader.persistent_workers and isinstance(loader.dataset, TrainPairs)
    assert isinstance(loader.sampler, EpochSampler)
    seen = []
    for e in range(3):
        epoch["now"] = e
        keys = [(k0, k1) for b in loader for k0, k1 in zip(b["key0"], b["key1"])]
        want = [(f"{p.scene}/{p.name0}", f"{p.scene}/{p.name1}") for p in dm.train_pairs(e)]
        assert sorted(keys) == sorted(want)  # exactly epoch e's pairs, each once
        seen.append(sorted(keys))
    assert seen[0] != seen[1] != seen[2]  # resampled, by the same workers
    batch = next(iter(loader))
    assert batch["img0"].dtype == torch.uint8  # un-augmented: uint8 until the device


def test_lightning_fit_draws_each_epochs_pairs_through_persistent_workers(tiny_root, tmp_path, monkeypatch):
    from mapfree.rpr.module import RPRModule
    from mapfree.rpr.train import TrainerOptions, fit

    seen: dict[int, list] = {}
    step = RPRModule.training_step

    def recording_step(self, batch, batch_idx):
        seen.setdefault(self.current_epoch, []).extend(zip(batch["key0"], batch["key1"]))
        return step(self, batch, batch_idx)

    monkeypatch.setattr(RPRModule, "training_step", recording_step)
    cfg = tiny_config(tiny_root, num_workers=1, batch_size=2, cache_dir=str(tmp_path / "cache"))
    cfg.train.max_epochs = 3
    trainer, _ = fit(
        cfg, tmp_path / "run", TrainerOptions(accelerator="cpu", devices=1, progress=False, limit_val_batches=1)
    )
    dm = RPRDataModule(cfg.data)
    dm.setup("fit")
    for e in range(3):
        want = [(f"{p.scene}/{p.name0}", f"{p.scene}/{p.name1}") for p in dm.train_pairs(e)]
        assert sorted(seen[e]) == sorted(want), e
    assert sorted(seen[0]) != sorted(seen[1]) != sorted(seen[2])
    assert trainer.train_dataloader.persistent_workers  # one loader, built once
    assert len(list((tmp_path / "cache").rglob("*.npy"))) > 0  # frames decoded once into the cache

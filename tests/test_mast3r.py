"""MASt3R / DUSt3R port: every output of the public networks on fill-rule weights (shared/fixtures/mast3r),
loaded through our checkpoint reader in both published forms, plus matches, preprocessing and loader errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
import torch

from fixture_tolerance import check, exceeded, vector_errors
from mapfree.mast3r.checkpoint import find_checkpoint, load_model, model_from_state_dict, read_checkpoint
from mapfree.mast3r.config import UnsupportedCheckpointError, config_from_kwargs, parse_constructor
from mapfree.mast3r.preprocess import prepare_image, prepare_path
from mapfree.mast3r.reciprocal import reciprocal_matches
from mapfree.weights import MissingWeightsError
from mapfree_dev.standins.mast3r import iter_synthetic_state_dict, save_hub, save_pth, synthetic_state_dict

INPUTS = ("landscape_96x128", "portrait_128x96")


@pytest.fixture(scope="module")
def fixture(mast3r_fixture: Path) -> tuple[dict, dict[str, np.ndarray]]:
    spec = json.loads((mast3r_fixture / "mast3r.json").read_text())
    with np.load(mast3r_fixture / "mast3r_outputs.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return spec, arrays


@pytest.fixture(scope="module")
def tiny(fixture):
    """Per tiny model: (constructor expression, fill-rule state dict), built once for the module."""
    spec, _ = fixture
    out = {}
    for model in ("mast3r-tiny", "dust3r-tiny"):
        expr = spec["models"][model]["expr"]
        out[model] = expr, synthetic_state_dict(config_from_kwargs(*parse_constructor(expr)))
    return out


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    yield


def _assert_close(got: np.ndarray, want: np.ndarray, what: str) -> None:
    """Within the tolerance of its kind of output (tests/fixture_tolerance.py: set from the CPU kernels' spread)."""
    key = what.rsplit(".", 1)[-1].removesuffix("_in_other_view")
    check(what, f"mast3r.{key}", vector_errors(got, want))


def _compare(net: torch.nn.Module, arrays: dict[str, np.ndarray], model: str, inputs=INPUTS, step: int = 1) -> int:
    n = 0
    for inp in inputs:
        x = torch.from_numpy(arrays[f"input.{inp}"])
        with torch.no_grad():
            preds = net(x[:1], x[1:])
        prefix = f"{model}.{inp}" + (f".step{step}" if step > 1 else "")
        for view, res in zip(("pred1", "pred2"), preds):
            for key, value in res.items():
                want = arrays[f"{prefix}.{view}.{key}"]
                _assert_close(value[0, ::step, ::step].numpy(), want, f"{prefix}.{view}.{key}")
                n += 1
    expected = sum(1 for k in arrays if k.startswith(f"{model}.") and ".pred" in k)
    assert n == expected  # every array of the fixture for this model was compared
    return n


@pytest.mark.parametrize("model", ["mast3r-tiny", "dust3r-tiny"])
@pytest.mark.parametrize(
    "form",
    [
        "pth",
        pytest.param("hub", marks=pytest.mark.slow),  # the forms: in `make test`
        pytest.param("hub-bin", marks=pytest.mark.slow),
    ],
)
def test_tiny_models_reproduce_public_outputs(fixture, tiny, model, form, tmp_path):
    spec, arrays = fixture
    m = spec["models"][model]
    sd = tiny[model][1]
    # our module names are exactly the published layout (strict loading accepts exactly these keys)
    assert {k: [str(v.dtype).replace("torch.", ""), list(v.shape)] for k, v in sd.items()} == m["state_dict"]
    path = save_pth(tmp_path / "m.pth", m["expr"], sd) if form == "pth" else save_hub(tmp_path / "hub", m["expr"], sd)
    if form == "hub-bin":  # older hub pushes: pytorch_model.bin instead of model.safetensors
        (path / "model.safetensors").unlink()
        torch.save(sd, path / "pytorch_model.bin")
    net = load_model(path)
    assert net.cfg.has_descriptors == model.startswith("mast3r")
    _compare(net, arrays, model)


@pytest.mark.parametrize(
    "key",
    [
        "enc_blocks.0.attn.qkv.weight",
        "dec_blocks.0.mlp.fc1.weight",
        "dec_blocks2.1.attn.proj.weight",
        "downstream_head1.dpt.head.0.weight",
        "downstream_head2.head_local_features.fc2.weight",
    ],
)
def test_one_weight_off_fails_the_tolerances(fixture, tiny, key):
    """No tolerance is wide enough to hide a port error: one scalar weight 1 % off (encoder, either decoder, either
    head) puts some output of the pair out of tolerance, on the CPU the tests run on."""
    _, arrays = fixture
    expr, sd = tiny["mast3r-tiny"]
    sd = {**sd, key: sd[key].clone()}
    sd[key].view(-1)[0] *= 1.01
    net = model_from_state_dict(config_from_kwargs(*parse_constructor(expr)), sd)
    x = torch.from_numpy(arrays["input.landscape_96x128"])
    with torch.no_grad():
        preds = net(x[:1], x[1:])
    broken = [
        f"{view}.{k}"
        for view, res in zip(("pred1", "pred2"), preds)
        for k, v in res.items()
        if exceeded(
            f"mast3r.{k.removesuffix('_in_other_view')}",
            vector_errors(v[0].numpy(), arrays[f"mast3r-tiny.landscape_96x128.{view}.{k}"]),
        )
    ]
    assert broken, f"{key} 1 % off passes every tolerance"


def test_checkpoint_without_second_decoder_gets_a_copy(tiny, tmp_path):
    expr, full = tiny["dust3r-tiny"]
    sd = {k: v for k, v in full.items() if not k.startswith("dec_blocks2.")}
    net = load_model(save_pth(tmp_path / "m.pth", expr, sd))
    for k, v in net.state_dict().items():
        if k.startswith("dec_blocks2."):
            assert torch.equal(v, sd["dec_blocks." + k[len("dec_blocks2.") :]])


@pytest.mark.slow
def test_reciprocal_matches_identical_to_public(fixture, tiny):
    spec, arrays = fixture
    expr, sd = tiny["mast3r-tiny"]
    net = model_from_state_dict(config_from_kwargs(*parse_constructor(expr)), sd)
    for inp in INPUTS:
        x = torch.from_numpy(arrays[f"input.{inp}"])
        with torch.no_grad():
            r1, r2 = net(x[:1], x[1:])
        for s in (8, 4):
            want = arrays[f"mast3r-tiny.{inp}.matches_s{s}"]
            xy1, xy2 = reciprocal_matches(r1["desc"][0], r2["desc"][0], subsample=s)
            np.testing.assert_array_equal(np.concatenate([xy1, xy2], axis=1), want)
            # the brute-force torch path (the GPU one) finds the same matches, by L2 or by dot product
            for dist in ("l2", "dot"):
                t1, t2 = reciprocal_matches(r1["desc"][0], r2["desc"][0], subsample=s, dist=dist, brute_force=True)
                np.testing.assert_array_equal(np.concatenate([t1, t2], axis=1), want)


def test_preprocessing_matches_public_loader_on_real_photos(fixture, realmini):
    spec, _ = fixture
    info = spec["load_images_512"]
    for rel, want in info["files"].items():
        p = prepare_path(realmini / "val" / rel)
        t = p.tensor[0].numpy().astype(np.float64)
        h, w = p.true_shape
        assert [h, w] == want["true_shape_hw"] and list(p.original_size) == want["source_size_wh"]
        assert t.mean() == pytest.approx(want["mean"], abs=1e-9)
        assert t.std() == pytest.approx(want["std"], abs=1e-9)
        np.testing.assert_array_equal(t[:, :3, :3], np.array(want["corner_3x3_rgb"]))
        np.testing.assert_array_equal(t[:, h // 2 : h // 2 + 3, w // 2 : w // 2 + 3], np.array(want["center_3x3_rgb"]))
    for wh, hw in info["sizes_wh_to_true_shape_hw"].items():
        w, h = map(int, wh.split("x"))
        assert list(prepare_image(PIL.Image.new("RGB", (w, h))).true_shape) == hw, wh


def test_network_pixels_map_back_to_original_pixels():
    p = prepare_image(PIL.Image.new("RGB", (540, 360)))  # resized 512x341, cropped to 512x336 from row 2
    assert p.resized_size == (512, 341) and p.crop == (0, 2, 512, 338)
    corners = p.to_original(np.array([[-0.5, -0.5], [511.5, 335.5]]))
    np.testing.assert_allclose(corners, [[-0.5, 2 * 360 / 341 - 0.5], [539.5, 338 * 360 / 341 - 0.5]])


@pytest.mark.parametrize(
    "expr, bad",
    [
        (
            "AsymmetricMASt3R(pos_embed='RoPE100', head_type='catmlp+dpt', output_mode='pts3d+desc24', dec_depth=12, "
            "use_flash=True)",
            "use_flash",
        ),
        ("AsymmetricCroCo3DStereo(pos_embed='cosine', head_type='dpt', dec_depth=12)", "pos_embed"),
        ("AsymmetricCroCo3DStereo(pos_embed='RoPE100', head_type='linear', dec_depth=12)", "head_type"),
        (
            "AsymmetricCroCo3DStereo(pos_embed='RoPE100', head_type='dpt', dec_depth=12, depth_mode=__import__('os'))",
            "depth_mode",
        ),
        ("CroCoNet(enc_depth=2)", "CroCoNet"),
    ],
)
def test_unsupported_checkpoint_argument_is_a_clear_error(expr, bad, tmp_path):
    path = save_pth(tmp_path / "bad.pth", expr, {})
    with pytest.raises(UnsupportedCheckpointError) as e:
        read_checkpoint(path)
    assert bad in str(e.value) and str(path) in str(e.value)


def test_state_dict_that_does_not_fit_is_a_clear_error(tiny, tmp_path):
    expr, sd = tiny["dust3r-tiny"]
    path = save_pth(tmp_path / "m.pth", expr, {**sd, "extra.weight": torch.zeros(1)})
    with pytest.raises(ValueError, match="1 unexpected"):
        load_model(path)


def test_missing_weights_name_the_file_the_folder_and_the_source(tmp_path, monkeypatch):
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path))
    with pytest.raises(MissingWeightsError) as e:
        find_checkpoint("mast3r")
    msg = str(e.value)
    assert "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth" in msg and str(tmp_path) in msg
    assert "naver/MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric" in msg and "MAPFREE_WEIGHTS_DIR" in msg
    with pytest.raises(MissingWeightsError, match="DUSt3R_ViTLarge_BaseDecoder_512_dpt"):
        find_checkpoint("dust3r")
    (tmp_path / "DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth").write_bytes(b"")
    assert find_checkpoint("dust3r").name == "DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth"


@pytest.mark.slow
@pytest.mark.parametrize("model", ["mast3r-full", "dust3r-full"])
def test_full_size_models_reproduce_public_outputs(fixture, model):
    """The published ViT-L architectures, weights generated tensor by tensor (one copy in memory)."""
    spec, arrays = fixture
    cfg = config_from_kwargs(*parse_constructor(spec["models"][model]["expr"]))
    with torch.device("meta"):
        from mapfree.mast3r.model import AsymmetricModel

        net = AsymmetricModel(cfg)
    layout = spec["models"][model]["state_dict"]
    assert set(net.state_dict()) == set(layout)
    for key, value in iter_synthetic_state_dict(cfg):
        assert list(value.shape) == layout[key][1]
        net.load_state_dict({key: value}, strict=False, assign=True)
    net.eval()
    _compare(net, arrays, model, inputs=("landscape_96x128",), step=4)


class _NotAllowed:
    """A class a checkpoint must not be able to make us construct."""


def test_unreadable_or_unsafe_checkpoint_is_a_clear_error(tmp_path):
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a checkpoint")
    unsafe = tmp_path / "unsafe.pth"
    torch.save({"model": {}, "args": _NotAllowed()}, unsafe)  # weights-only loading refuses other classes
    for path, refused in (
        (garbage, r"is refused: text, not weights"),
        (unsafe, "not a readable MASt3R/DUSt3R checkpoint"),
    ):
        with pytest.raises(ValueError, match=refused) as e:
            read_checkpoint(path)
        assert str(path) in str(e.value) and "weights_only" not in str(e.value)

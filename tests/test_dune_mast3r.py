"""DUNE-MASt3R port: every output of the public network on fill-rule weights (shared/fixtures/dune-mast3r),
loaded through our reader from files in the published layouts (decoder with or without the encoder, encoder
file found by name), the reciprocal matches, the 518 / patch-14 loader, and one-line errors for bad files."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
import torch

from mapfree.mast3r.checkpoint import load_strict
from mapfree.mast3r.config import UnsupportedCheckpointError
from mapfree.mast3r.dune import DuneMast3rModel
from mapfree.mast3r.dune_checkpoint import find_dune_checkpoint, load_dune_model
from mapfree.mast3r.preprocess import prepare_image, prepare_path
from mapfree.mast3r.reciprocal import reciprocal_matches
from mapfree.weights import BrokenWeightsError, MissingWeightsError
from mapfree_dev.standins.dune import (
    architecture,
    filled_state_dict,
    iter_filled_state_dict,
    save_decoder,
    save_encoder,
)

TINY = ("dune-small-tiny", "dune-base-tiny")
INPUTS = ("landscape_98x126", "portrait_126x98", "square_56x56")
#: The fixture README's tolerances: pts3d per point against its norm, conf / desc_conf relative, desc and the
#: DUNE features absolute.
RTOL, DESC_ATOL, FEAT_ATOL = 1e-4, 1e-5, 1e-4


@pytest.fixture(scope="module")
def fixture(dune_fixture: Path) -> tuple[dict, dict[str, np.ndarray]]:
    spec = json.loads((dune_fixture / "dune_mast3r.json").read_text())
    with np.load(dune_fixture / "dune_mast3r_outputs.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return spec, arrays


def _arch(spec: dict, model: str):
    m = spec["models"][model]
    args = m["dune_encoder"]["checkpoint_args"]
    return architecture(m["mast3r_model_str"], args["image_size"], args["enc_args"])


@pytest.fixture(scope="module")
def tiny(fixture):
    """Per tiny model: its fill-rule state dict (the whole model's keys), built once for the module."""
    spec, _ = fixture
    return {m: filled_state_dict(*_arch(spec, m)) for m in TINY}


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    yield


def max_error(got: np.ndarray, want: np.ndarray, key: str) -> float:
    """The README's measure: pts3d per point against its norm, conf/desc_conf relative, desc/feat absolute."""
    assert got.shape == want.shape, key
    if key in ("desc", "feat1", "feat2"):
        return float(np.abs(got - want).max())
    if want.ndim == 3:
        return float((np.linalg.norm(got - want, axis=-1) / np.linalg.norm(want, axis=-1)).max())
    return float((np.abs(got - want) / np.abs(want)).max())


def _tolerance(key: str) -> float:
    return DESC_ATOL if key == "desc" else FEAT_ATOL if key.startswith("feat") else RTOL


def compare(net: DuneMast3rModel, arrays: dict[str, np.ndarray], model: str, step: int = 1) -> dict[str, float]:
    """Run ``net`` on every input the fixture holds for ``model``; each array's error (asserting the tolerance)."""
    errors = {}
    for inp in INPUTS:
        prefix = f"{model}.{inp}" + (f".step{step}" if step > 1 else "")
        if f"{prefix}.pred1.conf" not in arrays:
            continue
        x = torch.from_numpy(arrays[f"input.{inp}"])
        with torch.no_grad():
            preds = net(x[:1], x[1:])
            feats = {"feat1": net.features(x[:1]), "feat2": net.features(x[1:])}
        got = {
            f"{view}.{k}": v[0, ::step, ::step].numpy()
            for view, r in zip(("pred1", "pred2"), preds)
            for k, v in r.items()
        }
        got.update({k: v[0].numpy() for k, v in feats.items() if f"{prefix}.{k}" in arrays})
        for name, value in got.items():
            key = name.rsplit(".", 1)[-1]
            err = max_error(value, arrays[f"{prefix}.{name}"], key)
            assert err < _tolerance(key), f"{prefix}.{name}: max error {err:.2e}"
            errors[f"{prefix}.{name}"] = err
    expected = {k for k in arrays if k.startswith(f"{model}.") and ".matches" not in k}
    assert set(errors) == expected  # every array of the fixture for this model was compared
    return errors


@pytest.mark.parametrize("model", TINY)
@pytest.mark.parametrize("form", ["decoder with encoder", "decoder + encoder file"])
def test_tiny_models_reproduce_public_outputs(fixture, tiny, model, form, tmp_path, monkeypatch):
    spec, arrays = fixture
    m = spec["models"][model]
    sd = tiny[model]
    assert set(sd) == set(m["state_dict"])  # exactly the public keys, with their shapes
    assert all(list(sd[k].shape) == shape for k, (_, shape) in m["state_dict"].items())
    name, model_str = m["dune_backbone_name"], m["mast3r_model_str"]
    dec = save_decoder(tmp_path / "dec.pth", name, model_str, sd, with_encoder=form == "decoder with encoder")
    if form == "decoder + encoder file":  # a backbone name no server knows: the reader is given the file
        args = m["dune_encoder"]["checkpoint_args"]
        enc = save_encoder(tmp_path / "enc" / "e.pth", args["image_size"], args["enc_args"], sd)
        net = load_dune_model(dec, encoder=enc)
    else:
        net = load_dune_model(dec)
    compare(net, arrays, model)


def test_unused_tensors_change_no_output(fixture, tiny):
    """The tensors the README lists as never read (DUNE's final norm, MASt3R's own encoder) may be NaN."""
    spec, arrays = fixture
    m = spec["models"]["dune-small-tiny"]
    sd = dict(tiny["dune-small-tiny"])
    for k in m["unused_in_forward"]:
        sd[k] = torch.full_like(sd[k], float("nan"))
    cfg, shape = _arch(spec, "dune-small-tiny")
    with torch.device("meta"):
        net = DuneMast3rModel(cfg, shape)
    compare(load_strict(net, sd, "filled", "DUNE-MASt3R"), arrays, "dune-small-tiny")


def test_one_changed_weight_fails_the_comparison(fixture, tiny):
    """The tolerances are tight enough to see one perturbed weight of the encoder."""
    spec, arrays = fixture
    sd = dict(tiny["dune-base-tiny"])
    w = sd["dune_backbone.blocks.0.1.mlp.fc1.weight"].clone()
    w[0, 0] += 1e-3
    sd["dune_backbone.blocks.0.1.mlp.fc1.weight"] = w
    cfg, shape = _arch(spec, "dune-base-tiny")
    with torch.device("meta"):
        net = DuneMast3rModel(cfg, shape)
    with pytest.raises(AssertionError, match="max error"):
        compare(load_strict(net, sd, "perturbed", "DUNE-MASt3R"), arrays, "dune-base-tiny")


@pytest.mark.parametrize("model", [TINY[0], pytest.param(TINY[1], marks=pytest.mark.slow)])
def test_reciprocal_matches_identical_to_public(fixture, model):
    """Our matcher on the stored descriptors gives the public matches (KD-tree L2 and brute-force dot)."""
    _, arrays = fixture
    for inp in INPUTS[:2]:
        d1 = torch.from_numpy(arrays[f"{model}.{inp}.pred1.desc"])
        d2 = torch.from_numpy(arrays[f"{model}.{inp}.pred2.desc"])
        for s in (8, 4):
            want = arrays[f"{model}.{inp}.matches_s{s}"]
            np.testing.assert_array_equal(arrays[f"{model}.{inp}.matches_dot_s{s}"], want)
            xy1, xy2 = reciprocal_matches(d1, d2, subsample=s)
            np.testing.assert_array_equal(np.concatenate([xy1, xy2], axis=1), want)
            t1, t2 = reciprocal_matches(d1, d2, subsample=s, dist="dot", brute_force=True)
            np.testing.assert_array_equal(np.concatenate([t1, t2], axis=1), want)


def test_loader_at_518_matches_public_on_real_photos(fixture, realmini):
    spec, _ = fixture
    info = spec["load_images_518"]
    for rel, want in info["files"].items():
        p = prepare_path(realmini / "val" / rel, 518, patch=14, square_ok=True)
        t = p.tensor[0].numpy().astype(np.float64)
        h, w = p.true_shape
        assert [h, w] == want["true_shape_hw"] and list(p.original_size) == want["source_size_wh"]
        assert t.mean() == pytest.approx(want["mean"], abs=1e-9)
        assert t.std() == pytest.approx(want["std"], abs=1e-9)
        checksum = float(np.sum((t * np.arange(t.size).reshape(t.shape)) % 7))
        assert checksum == pytest.approx(want["checksum"], rel=1e-12)
        np.testing.assert_array_equal(t[:, :3, :3], np.array(want["corner_3x3_rgb"]))
        np.testing.assert_array_equal(t[:, h // 2 : h // 2 + 3, w // 2 : w // 2 + 3], np.array(want["center_3x3_rgb"]))
    for wh, hw in info["sizes_wh_to_true_shape_hw"].items():
        w, h = map(int, wh.split("x"))
        assert list(prepare_image(PIL.Image.new("RGB", (w, h)), 518, patch=14, square_ok=True).true_shape) == hw, wh


def test_views_of_different_shapes_pair_as_in_mast3r(fixture, tiny):
    """A landscape reference with a portrait query (the public class fails there: its branch for views of
    different shapes unpacks three values from two): each view encoded at its own size, each map at its own."""
    spec, arrays = fixture
    cfg, shape = _arch(spec, "dune-small-tiny")
    with torch.device("meta"):
        net = DuneMast3rModel(cfg, shape)
    net = load_strict(net, tiny["dune-small-tiny"], "filled", "DUNE-MASt3R")
    land, port = (torch.from_numpy(arrays[f"input.{k}"]) for k in INPUTS[:2])
    with torch.no_grad():
        e1, e2 = net.encode(land[:1]), net.encode(port[1:])
        r1, r2 = net.predict(e1, e2)
    assert e1.tokens.shape[1] == 7 * 9 and e2.tokens.shape[1] == 9 * 7
    assert r1["pts3d"].shape == (1, 98, 126, 3) and r2["pts3d_in_other_view"].shape == (1, 126, 98, 3)
    assert r2["desc"].shape == (1, 126, 98, 24) and all(torch.isfinite(v).all() for v in (*r1.values(), *r2.values()))


# ----------------------------------------------------------------------------------------------- bad files


def _tiny_files(spec, sd, folder: Path, model: str = "dune-small-tiny") -> tuple[Path, Path]:
    """A decoder without its encoder under the published ViT-S name, and the encoder file beside it."""
    m = spec["models"][model]
    args = m["dune_encoder"]["checkpoint_args"]
    dec = save_decoder(
        folder / "dunemast3r_cvpr25_vitsmall.pth", "dune_vitsmall_14_448_encoder", m["mast3r_model_str"], sd, False
    )
    enc = save_encoder(folder / "dune_vitsmall14_448.pth", args["image_size"], args["enc_args"], sd)
    return dec, enc


def test_encoder_file_found_by_name_in_the_weights_folder(fixture, tiny, tmp_path, monkeypatch):
    spec, arrays = fixture
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path))
    dec, _ = _tiny_files(spec, tiny["dune-small-tiny"], tmp_path)
    assert find_dune_checkpoint("dune-mast3r-small") == dec
    compare(load_dune_model(dec), arrays, "dune-small-tiny")


def test_decoder_without_its_encoder_names_the_encoder_file_and_its_source(fixture, tiny, tmp_path, monkeypatch):
    spec, _ = fixture
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path))
    dec, enc = _tiny_files(spec, tiny["dune-small-tiny"], tmp_path)
    enc.unlink()
    with pytest.raises(MissingWeightsError) as e:
        load_dune_model(dec)
    msg = str(e.value)
    assert "dune_vitsmall14_448.pth" in msg and str(tmp_path) in msg
    assert "https://download.europe.naverlabs.com/dune/dune_vitsmall14_448.pth" in msg
    assert "dunemast3r_cvpr25_vitsmall.pth holds no encoder" in msg


def test_encoder_of_the_wrong_width_is_named(fixture, tiny, tmp_path, monkeypatch):
    spec, _ = fixture
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path))
    dec, enc = _tiny_files(spec, tiny["dune-small-tiny"], tmp_path)
    base = spec["models"]["dune-base-tiny"]["dune_encoder"]["checkpoint_args"]
    save_encoder(enc, base["image_size"], base["enc_args"], tiny["dune-base-tiny"])  # 64 wide, decoder wants 48
    with pytest.raises(ValueError) as e:
        load_dune_model(dec)
    msg = str(e.value)
    assert str(enc) in msg and "width 64" in msg and "width 48" in msg and "\n" not in msg


def test_unknown_backbone_name_and_unsupported_string_are_named(fixture, tiny, tmp_path):
    spec, _ = fixture
    m = spec["models"]["dune-small-tiny"]
    sd = tiny["dune-small-tiny"]
    dec = save_decoder(tmp_path / "d.pth", "dune_vitgiant_encoder", m["mast3r_model_str"], sd, with_encoder=False)
    with pytest.raises(ValueError, match="unknown DUNE encoder dune_backbone_name='dune_vitgiant_encoder'"):
        load_dune_model(dec)
    bad = save_decoder(tmp_path / "b.pth", "x", m["mast3r_model_str"].replace("RoPE100", "cosine"), sd)
    with pytest.raises(UnsupportedCheckpointError, match="pos_embed") as e:
        load_dune_model(bad)
    assert str(bad) in str(e.value)
    dust3r = save_decoder(tmp_path / "c.pth", "x", "AsymmetricCroCo3DStereo(head_type='dpt', dec_depth=12)", sd)
    with pytest.raises(UnsupportedCheckpointError, match="not AsymmetricMASt3R"):
        load_dune_model(dust3r)


def test_truncated_or_foreign_files_are_one_clear_line(fixture, tiny, tmp_path):
    spec, _ = fixture
    dec, enc = _tiny_files(spec, tiny["dune-small-tiny"], tmp_path)
    cut = tmp_path / "cut.pth"
    cut.write_bytes(dec.read_bytes()[: dec.stat().st_size // 2])
    with pytest.raises(BrokenWeightsError, match="cut.pth is refused"):
        load_dune_model(cut)
    with pytest.raises(ValueError, match="not a DUNE-MASt3R decoder file"):
        load_dune_model(enc)  # the encoder file given as the decoder
    cut_enc = tmp_path / "e" / "dune_vitsmall14_448.pth"
    cut_enc.parent.mkdir()
    cut_enc.write_bytes(enc.read_bytes()[:1000])
    with pytest.raises(BrokenWeightsError, match="dune_vitsmall14_448.pth is refused"):
        load_dune_model(dec, encoder=cut_enc)


def test_decoder_file_missing_a_tensor_is_named(fixture, tiny, tmp_path):
    spec, _ = fixture
    m = spec["models"]["dune-small-tiny"]
    sd = {k: v for k, v in tiny["dune-small-tiny"].items() if not k.startswith("mast3r.dec_blocks2.")}
    dec = save_decoder(tmp_path / "d.pth", m["dune_backbone_name"], m["mast3r_model_str"], sd)
    with pytest.raises(ValueError, match=r"missing \(e.g. \['mast3r.dec_blocks2"):
        load_dune_model(dec)


# ----------------------------------------------------------------------------------------------- full size


def _full_model(spec: dict, model: str) -> DuneMast3rModel:
    """The published architecture with fill-rule weights, generated tensor by tensor (one copy in memory)."""
    cfg, shape = _arch(spec, model)
    with torch.device("meta"):
        net = DuneMast3rModel(cfg, shape)
    layout = spec["models"][model]["state_dict"]
    assert set(net.state_dict()) == set(layout)
    for key, value in iter_filled_state_dict(cfg, shape):
        assert list(value.shape) == layout[key][1]
        net.load_state_dict({key: value}, strict=False, assign=True)
    return net.eval()


@pytest.mark.slow
@pytest.mark.parametrize("model", ["dune-small-full", "dune-base-full"])
def test_full_size_models_reproduce_public_outputs(fixture, model):
    spec, arrays = fixture
    compare(_full_model(spec, model), arrays, model, step=4)


@pytest.mark.slow
def test_tolerances_hold_on_every_cpu_kernel_path_and_thread_count(dune_fixture, tmp_path):
    """The fixture comparison in fresh processes under ATen's default (no SIMD) kernels on one thread and its AVX2
    kernels on two: each kernel path and each thread count taken once, the README's tolerances hold on any x86-64 CPU."""
    script = (
        "import sys, torch, json, numpy as np; sys.path.insert(0, {tests!r}); torch.set_num_threads(int(sys.argv[1]))\n"
        "import test_dune_mast3r as t\n"
        "spec = json.loads(open({j!r}).read()); arrays = dict(np.load({n!r}))\n"
        "worst = {{}}\n"
        "for m in t.TINY:\n"
        "    for k, e in t.compare(t.load_dune_model(t.save_decoder({d!r} + m, spec['models'][m]['dune_backbone_name'], "
        "spec['models'][m]['mast3r_model_str'], t.filled_state_dict(*t._arch(spec, m)))), arrays, m).items():\n"
        "        worst[k.rsplit('.', 1)[-1]] = max(worst.get(k.rsplit('.', 1)[-1], 0), e)\n"
        "print(json.dumps(worst))\n"
    ).format(
        tests=str(Path(__file__).parent),
        j=str(dune_fixture / "dune_mast3r.json"),
        n=str(dune_fixture / "dune_mast3r_outputs.npz"),
        d=str(tmp_path / "dec-"),
    )
    for cap, threads in (("default", "1"), ("avx2", "2")):
        env = {**os.environ, "ATEN_CPU_CAPABILITY": cap, "OMP_NUM_THREADS": threads}
        r = subprocess.run([sys.executable, "-c", script, threads], capture_output=True, text=True, env=env)
        assert r.returncode == 0, (cap, threads, r.stderr[-2000:])
        worst = json.loads(r.stdout.strip().splitlines()[-1])
        for key, err in worst.items():
            assert err < _tolerance(key), (cap, threads, key, err)

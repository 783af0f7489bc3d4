"""The MASt3R family exported to ONNX and run by onnxruntime: the tiny fill-rule models of the shared fixture
exported once per module, their graphs checked by onnx.checker, their outputs against our PyTorch port and the
public code's arrays, reciprocal matches on real photos, the external-data path and every bad graph as one line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
import torch

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from mapfree.cli import main  # noqa: E402
from mapfree.mast3r.config import config_from_kwargs, parse_constructor  # noqa: E402
from mapfree.mast3r.export import input_shape  # noqa: E402
from mapfree.mast3r.model import AsymmetricModel  # noqa: E402
from mapfree.mast3r.onnxgraph import GraphError, OnnxPairNetwork, decoder_path, export_graphs  # noqa: E402
from mapfree.matching import MissingWeightsError  # noqa: E402
from mapfree.matching.mast3r import Mast3rMatcher  # noqa: E402
from mapfree_dev.standins.mast3r import save_pth, synthetic_state_dict  # noqa: E402

LONG = 128  # the fixture's landscape input is 96 x 128: a 4:3 photo at long side 128 prepares to the same
HW = (96, 128)
PAIRS = (("seq0/frame_00000.jpg", "seq1/frame_00010.jpg"), ("seq0/frame_00000.jpg", "seq1/frame_00020.jpg"))


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    yield


@pytest.fixture(scope="module")
def spec(mast3r_fixture):
    spec = json.loads((mast3r_fixture / "mast3r.json").read_text())
    with np.load(mast3r_fixture / "mast3r_outputs.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return spec, arrays


def _tiny(spec, kind: str) -> tuple[str, AsymmetricModel]:
    expr = spec[0]["models"][f"{kind}-tiny"]["expr"]
    cfg = config_from_kwargs(*parse_constructor(expr))
    model = AsymmetricModel(cfg)
    model.load_state_dict(synthetic_state_dict(cfg))
    return expr, model.eval()


@pytest.fixture(scope="module")
def mast3r(spec, tmp_path_factory):
    """The tiny MASt3R, its checkpoint file and its two graphs (exported once for the module)."""
    root = tmp_path_factory.mktemp("onnx")
    expr, model = _tiny(spec, "mast3r")
    pth = save_pth(root / "mast3r-tiny.pth", expr, model.state_dict())
    torch.set_num_threads(1)
    res = export_graphs(model, "mast3r", HW, root / "mast3r.onnx", long_side=LONG)
    return model, pth, res


@pytest.fixture(scope="module")
def ort_net(mast3r):
    return OnnxPairNetwork(mast3r[2].encoder, "mast3r", LONG)


def _relative(got: np.ndarray, want: np.ndarray) -> float:
    """Max error relative to each value (a vector: to its length), floored at 1% of the map's median size."""
    size = np.linalg.norm(want, axis=-1) if want.ndim == 3 else np.abs(want)
    diff = np.linalg.norm(got - want, axis=-1) if want.ndim == 3 else np.abs(got - want)
    return float((diff / np.maximum(size, 0.01 * np.median(size))).max())


def _predict(net, x: torch.Tensor):
    with torch.no_grad():
        return net.predict(net.encode(x[:1]), net.encode(x[1:]))


def test_graphs_are_checked_and_say_what_they_hold(mast3r, ort_net):
    _, _, res = mast3r
    assert res.files == (res.encoder, res.decoder) and res.decoder == decoder_path(res.encoder)
    for f in res.files:
        onnx.checker.check_model(str(f))
        model = onnx.load(str(f))
        assert model.opset_import[0].version == 17
        dims = model.graph.input[0].type.tensor_type.shape.dim
        assert dims[0].dim_param == "batch"  # dynamic batch
    assert [i.name for i in onnx.load(str(res.encoder)).graph.input] == ["image"]
    info = ort_net.decoder_info
    assert (info.kind, info.role, info.input_hw, info.long_side) == ("mast3r", "decoder", HW, LONG)
    assert ort_net.cfg == mast3r[0].cfg and ort_net.square_ok is False
    assert set(info.outputs) == {f"pred1.{k}" for k in ("pts3d", "conf", "desc", "desc_conf")} | {
        f"pred2.{k}" for k in ("pts3d_in_other_view", "conf", "desc", "desc_conf")
    }


def test_outputs_match_the_port_and_the_public_code(mast3r, ort_net, spec):
    model, _, _ = mast3r
    arrays = spec[1]
    x = torch.from_numpy(arrays["input.landscape_96x128"])
    got, ours = _predict(ort_net, x), _predict(model, x)
    n = 0
    for view, g, o in zip(("pred1", "pred2"), got, ours):
        assert set(g) == set(o)
        for key in g:
            assert g[key].dtype == torch.float32 and g[key].shape == o[key].shape
            assert _relative(g[key].numpy(), o[key].numpy()) < 1e-3, f"{view}.{key} vs the PyTorch port"
            public = arrays[f"mast3r-tiny.landscape_96x128.{view}.{key}"]
            assert _relative(g[key][0].numpy(), public) < 1e-3, f"{view}.{key} vs the public code"
            n += 1
    assert n == 8


def test_dynamic_batch_gives_each_pair_its_own_output(ort_net, spec):
    x = torch.from_numpy(spec[1]["input.landscape_96x128"])
    e = ort_net.encode(torch.cat([x[:1], x[1:], x[:1]]))  # 3 images in one pass
    assert e.tokens.shape[0] == 3
    r1, r2 = ort_net.predict(e, ort_net.encode(torch.cat([x[1:], x[:1], x[1:]])))
    alone1, alone2 = _predict(ort_net, x)
    assert _relative(r1["desc"][0].numpy(), alone1["desc"][0].numpy()) < 1e-5
    assert _relative(r2["pts3d_in_other_view"][2].numpy(), alone2["pts3d_in_other_view"][0].numpy()) < 1e-5


def _photos(realmini: Path, tmp: Path, crop: tuple[int, int, int, int] = (30, 0, 510, 360)) -> dict[str, np.ndarray]:
    """Real photos of s00000 cropped to 4:3 (480 x 360): at long side 128 they prepare to the fixture's 96 x 128."""
    out = {}
    for name in {n for pair in PAIRS for n in pair}:
        with PIL.Image.open(realmini / "val" / "s00000" / name) as im:
            out[name] = np.asarray(im.convert("RGB").crop(crop))
    return out


def test_real_photos_same_matches_reference_encoded_once(mast3r, realmini, tmp_path):
    _, pth, res = mast3r
    photos = _photos(realmini, tmp_path)
    torch_m = Mast3rMatcher(weights=str(pth), long_side=LONG, device="cpu")
    ort_m = Mast3rMatcher(backend="onnxruntime", onnx=str(res.encoder), long_side=LONG, device="cpu")
    assert ort_m.engine is not torch_m.engine and ort_m.engine.device.type == "cpu"
    ref = ort_m.extract(photos[PAIRS[0][0]])
    for a, b in PAIRS:
        want = torch_m.match(torch_m.extract(photos[a]), torch_m.extract(photos[b]))
        got = ort_m.match(ref, ort_m.extract(photos[b]))
        assert len(want) > 20
        same = {tuple(r) for r in np.c_[want.kpts0, want.kpts1].round(3)} & {
            tuple(r) for r in np.c_[got.kpts0, got.kpts1].round(3)
        }
        assert len(same) >= 0.98 * max(len(want), len(got)), f"{a} {b}: {len(same)} of {len(want)} / {len(got)}"
    assert ort_m.engine.encodes == 3  # the reference once, each query once


def test_a_graph_for_other_photos_says_how_to_export_one(ort_net):
    with pytest.raises(GraphError, match=r"takes 128x96 network inputs, but this image prepares to 96x128"):
        ort_net.encode(torch.zeros(1, 3, 128, 96))


def test_bad_graphs_are_one_line(mast3r, tmp_path, capsys):
    _, _, res = mast3r
    missing = tmp_path / "none.onnx"
    with pytest.raises(MissingWeightsError, match=r"none.onnx: not found; `mapfree export --matcher mast3r"):
        Mast3rMatcher(backend="onnxruntime", onnx=str(missing), long_side=LONG)
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(res.encoder.read_bytes()[:5000])  # a download cut short
    with pytest.raises(GraphError, match=r"broken.onnx: not a readable ONNX graph"):
        OnnxPairNetwork(broken, "mast3r", LONG)
    other = onnx.load(str(res.encoder))
    for p in other.metadata_props:
        if p.key == "mapfree.kind":
            p.value = "dust3r"
    onnx.save(other, str(tmp_path / "other.onnx"))
    with pytest.raises(GraphError, match=r"other.onnx: a graph of dust3r, not mast3r"):
        OnnxPairNetwork(tmp_path / "other.onnx", "mast3r", LONG)
    with pytest.raises(GraphError, match=r"exported for 128-pixel inputs, not 160 \(export with --size 160"):
        OnnxPairNetwork(res.encoder, "mast3r", 160)
    shutil.copy(res.encoder, tmp_path / "alone.onnx")  # no decoder beside it
    with pytest.raises(GraphError, match=r"alone.decoder.onnx: not found"):
        OnnxPairNetwork(tmp_path / "alone.onnx", "mast3r", LONG)
    plain = onnx.load(str(res.encoder))
    del plain.metadata_props[:]
    onnx.save(plain, str(tmp_path / "plain.onnx"))
    with pytest.raises(GraphError, match=r"plain.onnx: an ONNX graph without mapfree's metadata"):
        OnnxPairNetwork(tmp_path / "plain.onnx", "mast3r", LONG)
    # and through the command line: one line, exit 1
    img = tmp_path / "a.png"
    PIL.Image.fromarray(np.zeros((96, 128, 3), np.uint8)).save(img)
    argv = ["match", str(img), str(img), "--matcher", "mast3r", "--backend", "onnxruntime", "--onnx"]
    assert main([*argv, str(broken), "--option", f"long_side={LONG}"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("mapfree match: error: ") and "broken.onnx: not a readable ONNX graph" in err
    assert "\n" not in err


def test_export_refuses_what_it_cannot_write(tmp_path, capsys):
    assert main(["export", "--matcher", "sift", "-o", str(tmp_path / "x.onnx")]) == 1
    err = capsys.readouterr().err
    assert (
        err.strip()
        == "mapfree export: error: --matcher 'sift': not exportable (exportable: mast3r, dust3r, dune-mast3r, dune-mast3r-small)"
    )
    assert main(["export", "--matcher", "mast3r", "-o", str(tmp_path / "x.pth")]) == 1
    assert "the name must end in .onnx" in capsys.readouterr().err
    assert main(["export", "--matcher", "mast3r", "-o", str(tmp_path / "x.onnx"), "--photo-size", "big"]) == 1
    assert "--photo-size must look like 540x720" in capsys.readouterr().err
    missing = tmp_path / "nothing.pth"
    assert main(["export", "--matcher", "dust3r", "-o", str(tmp_path / "x.onnx"), "--weights", str(missing)]) == 1
    last = capsys.readouterr().err.strip().splitlines()[-1]  # after the progress lines
    assert last.startswith("mapfree export: error: dust3r: checkpoint ") and "nothing.pth not found" in last
    assert not (tmp_path / "x.onnx").exists()


def test_input_shape_is_the_port_preprocessing():
    assert input_shape((540, 720), 512) == (512, 384)  # Map-free photos at the published size
    assert input_shape((540, 360), 512) == (336, 512)
    assert input_shape((480, 360), LONG) == HW


@pytest.mark.slow
def test_cli_exports_dust3r_with_external_data(spec, tmp_path, capsys):
    """DUSt3R through ``mapfree export`` with the weights forced out of the graphs (the path a ViT-L takes past
    2 GiB), checked by path, run by onnxruntime to the port's outputs."""
    expr, model = _tiny(spec, "dust3r")
    pth = save_pth(tmp_path / "dust3r-tiny.pth", expr, model.state_dict())
    out = tmp_path / "graphs" / "dust3r.onnx"
    argv = ["export", "--matcher", "dust3r", "-o", str(out), "--weights", str(pth), "--size", str(LONG)]
    assert main([*argv, "--photo-size", "480x360", "--external-data"]) == 0
    line = capsys.readouterr().out
    assert "dust3r: wrote" in line and "opset 17" in line and "input 128x96" in line
    data = sum(f.with_name(f.name + ".data").stat().st_size for f in (out, decoder_path(out)))
    assert data > 0.9 * sum(p.numel() * 4 for p in model.parameters())  # the weights are in the .data files
    for f in (out, decoder_path(out)):
        assert f.stat().st_size < 0.05 * data  # the graphs alone (the small constants stay inline)
        onnx.checker.check_model(str(f))
    net = OnnxPairNetwork(out, "dust3r", LONG)
    assert not net.cfg.has_descriptors
    x = torch.from_numpy(spec[1]["input.landscape_96x128"])
    for g, o in zip(_predict(net, x), _predict(model, x)):
        assert set(g) == set(o) and all(_relative(g[k].numpy(), o[k].numpy()) < 1e-3 for k in g)


def test_method_yaml_and_relocalization_api_run_the_graphs(mast3r, realmini, tmp_path, monkeypatch):
    """A method whose matcher_opts name the backend (as a YAML for ``mapfree run`` does) through the relocalization
    API's anchors: the reference prepared once, each query one encoder and one decoder pass in onnxruntime."""
    from mapfree import methods
    from mapfree.data import Dataset
    from mapfree.mast3r.engine import shared_engine
    from mapfree.service.anchors.localizers import Localizers, Photo

    res = mast3r[2]
    yaml = tmp_path / "mast3r-onnx.yaml"
    yaml.write_text(
        f"extends: mast3r_pnp_mast3r\nmatcher_opts:\n  long_side: {LONG}\n  backend: onnxruntime\n"
        f"  onnx: {res.encoder}\n  device: cpu\n"
    )
    method = methods.load_yaml(yaml)
    assert method.matcher_opts["backend"] == "onnxruntime"
    monkeypatch.setitem(methods._REGISTRY, "mast3r-onnx-test", method)
    engine = shared_engine("mast3r", device="cpu", long_side=LONG, backend="onnxruntime", onnx=res.encoder)
    scene = Dataset(realmini).scene("val", "s00000")
    photos = _photos(realmini, tmp_path)
    K = scene.reference.intrinsics
    ref = Photo(photos[PAIRS[0][0]], K)
    locs = Localizers()
    enc0, fwd0 = engine.encodes, engine.forwards
    for _, query in PAIRS:
        est = locs.localize_photos("a1", "mast3r-onnx-test", "v1", lambda: [ref], photos[query], K)
        assert est.ok or est.reason
        assert est.matches is not None and len(est.matches) > 20
    assert engine.encodes - enc0 == 1 + len(PAIRS) and engine.forwards - fwd0 == len(PAIRS)


def test_dune_mast3r_exports_and_runs_to_the_public_outputs(dune_fixture, tmp_path):
    """DUNE-MASt3R (the tiny ViT-S of its fixture) through the same two graphs: its patch-14 DPT upsampling (a
    non-integer resize) and interpolated position embedding export, and onnxruntime gives the port's outputs and the
    public code's, and the same reciprocal matches."""
    from mapfree.mast3r.dune import DuneMast3rModel
    from mapfree.mast3r.reciprocal import reciprocal_matches
    from mapfree_dev.standins.dune import architecture, filled_state_dict

    spec = json.loads((dune_fixture / "dune_mast3r.json").read_text())
    with np.load(dune_fixture / "dune_mast3r_outputs.npz") as z:
        arrays = {k: z[k] for k in z.files}
    m = spec["models"]["dune-small-tiny"]
    args = m["dune_encoder"]["checkpoint_args"]
    cfg, shape = architecture(m["mast3r_model_str"], args["image_size"], args["enc_args"])
    model = DuneMast3rModel(cfg, shape)
    model.load_state_dict(filled_state_dict(cfg, shape))
    model.eval()
    assert input_shape((126, 98), 126, 14, True) == (98, 126)  # the 518-style loader at patch 14
    res = export_graphs(model, "dune-mast3r-small", (98, 126), tmp_path / "dune.onnx", long_side=126)
    for f in res.files:
        onnx.checker.check_model(str(f))
    net = OnnxPairNetwork(res.encoder, "dune-mast3r-small", 126)
    assert net.cfg.patch_size == 14 and net.square_ok is True
    x = torch.from_numpy(arrays["input.landscape_98x126"])
    got, ours = _predict(net, x), _predict(model, x)
    for view, g, o in zip(("pred1", "pred2"), got, ours):
        for key in g:
            assert _relative(g[key].numpy(), o[key].numpy()) < 1e-3, f"{view}.{key} vs the PyTorch port"
            public = arrays[f"dune-small-tiny.landscape_98x126.{view}.{key}"]
            assert _relative(g[key][0].numpy(), public) < 1e-3, f"{view}.{key} vs the public code"
    xy1, xy2 = reciprocal_matches(got[0]["desc"][0], got[1]["desc"][0], subsample=8)
    want = arrays["dune-small-tiny.landscape_98x126.matches_s8"]
    same = len({tuple(r) for r in np.concatenate([xy1, xy2], axis=1)} & {tuple(r) for r in want})
    assert same >= 0.98 * len(want)

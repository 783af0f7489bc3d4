"""The published Map-free RPR checkpoints: all 12 configurations load by key and give the public code's poses.

``shared/fixtures/official-rpr`` records what the public network code outputs for each configuration when every
tensor of its checkpoint is filled by a fixed rule; here we write such a checkpoint, load it through our
public-checkpoint path and compare R, t on the same inputs (binned variants exactly, the others to 1e-4).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("pytorch_lightning")

from fixture_tolerance import absolute, check, exceeded  # noqa: E402
from mapfree.rpr.official import OFFICIAL_CONFIGS
from mapfree_dev.standins.mast3r import fill_value  # noqa: E402  (the same fill rule as the MASt3R fixture)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def fill_state_dict(spec: dict[str, list]) -> dict[str, torch.Tensor]:
    """The fixture's fill rule (its README): a deterministic value for every key of a checkpoint."""
    sd = {}
    for key, (dtype, shape) in spec.items():
        if not dtype.startswith("float"):
            sd[key] = torch.zeros(shape, dtype=getattr(torch, dtype))
            continue
        sd[key] = torch.from_numpy(fill_value(key, tuple(shape)))
    return sd


@pytest.fixture(scope="module")
def official(official_rpr) -> dict:
    return json.loads((official_rpr / "official_rpr.json").read_text())


@pytest.fixture(scope="module")
def inputs() -> tuple[torch.Tensor, torch.Tensor]:
    x = np.random.default_rng(2022).random((2, 2, 3, 360, 270)).astype(np.float32)
    return torch.from_numpy(x[0]), torch.from_numpy(x[1])


def write_checkpoint(official: dict, name: str, folder: Path) -> Path:
    """A checkpoint shaped as the published ones: Lightning's dict with the public ``state_dict``."""
    path = folder / f"{name}.ckpt"
    if not path.is_file():
        folder.mkdir(parents=True, exist_ok=True)
        torch.save(
            {
                "epoch": 49,
                "global_step": 0,
                "pytorch-lightning_version": "1.6.5",
                "state_dict": fill_state_dict(official[name]["state_dict"]),
            },
            path,
        )
    return path


@pytest.fixture(scope="module")
def weights(official, tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("weights")


@pytest.fixture(scope="module")
def encoder_features(official, weights, inputs):
    """Both images' encoder features through the loaded 3d3d checkpoint (every release shares this encoder)."""
    from mapfree.rpr import load_method

    net = load_method(write_checkpoint(official, "3d3d", weights), device="cpu").module.net
    with torch.no_grad():
        return net.encoder(inputs[0]), net.encoder(inputs[1]), net.encoder.state_dict()


def test_fixture_lists_the_twelve_published_configurations(official):
    assert sorted(official) == sorted(OFFICIAL_CONFIGS)
    for name in OFFICIAL_CONFIGS:
        assert official[name]["config"] == f"config/regression/mapfree/{name}.yaml"


# Two configurations (a 3D-3D head and a binned one) in `make test-fast`; all twelve in `make test`.
@pytest.mark.parametrize(
    "name",
    [
        c if c in ("3d3d", "rotbin_transdirectionbin_scale") else pytest.param(c, marks=pytest.mark.slow)
        for c in OFFICIAL_CONFIGS
    ],
)
def test_published_checkpoint_loads_strictly_and_gives_the_public_pose(
    name, official, weights, inputs, encoder_features
):
    from mapfree.rpr import load_method

    method = load_method(write_checkpoint(official, name, weights), device="cpu")  # config from the file name
    module = method.module
    assert not module.training and method.cfg.model.uncertainty is False
    # Strict: our module holds exactly the checkpoint's keys, in its shapes (s_r/s_t are the loss weights).
    ours = {k.removeprefix("net."): v for k, v in module.state_dict().items()}
    ours = {{"criterion.s_rot": "s_r", "criterion.s_trans": "s_t"}.get(k, k): v for k, v in ours.items()}
    spec = official[name]["state_dict"]
    assert set(ours) == set(spec)
    for k, (dtype, shape) in spec.items():
        assert list(ours[k].shape) == shape and str(ours[k].dtype) == f"torch.{dtype}", k
    # Every release shares the encoder's keys and fill, so its features are computed once (encoder_features)
    # after checking that this checkpoint's encoder is bit-identical; the 3d3d case runs the whole forward.
    f0, f1, enc_state = encoder_features
    for k, v in module.net.encoder.state_dict().items():
        assert torch.equal(v, enc_state[k]), k
    with torch.no_grad():
        out = module.net(*inputs) if name == "3d3d" else module.net.from_features(f0, f1)
    R, t = out.R.numpy(), out.t.numpy().reshape(2, 1, 3)
    R_pub, t_pub = np.array(official[name]["R"]), np.array(official[name]["t"])
    assert np.isfinite(R).all() and np.isfinite(t).all()
    if name.startswith("rotbin"):
        assert np.array_equal(R.astype(np.float32), R_pub.astype(np.float32))  # argmax bins: exactly
    else:
        check(f"{name}.R", "rpr.R", absolute(R, R_pub))
    if name.startswith("rotbin_transdirectionbin"):
        np.testing.assert_allclose(t, t_pub, atol=1e-6, rtol=0)  # binned direction, regressed scale
    else:
        check(f"{name}.t", "rpr.t", absolute(t, t_pub))
    # The two pairs differ, so a network that ignored its inputs would not pass.
    assert np.abs(R_pub[0] - R_pub[1]).max() > 1e-3 or np.abs(t_pub[0] - t_pub[1]).max() > 1e-3


@pytest.mark.parametrize("key", ["encoder.firstconv.weight", "head.resblock2.conv1.weight"])
def test_one_weight_off_fails_the_tolerances(official, inputs, tmp_path, key):
    """No tolerance is wide enough to hide a port error: one weight tensor 1 % off (a scalar 1 % off moves these small networks' outputs less than float32 rounding does) moves the pose out of it."""
    from mapfree.rpr import load_method

    sd = fill_state_dict(official["3d3d"]["state_dict"])
    sd[key] = sd[key] * 1.01
    torch.save({"epoch": 49, "global_step": 0, "state_dict": sd}, tmp_path / "3d3d.ckpt")
    with torch.no_grad():
        out = load_method(tmp_path / "3d3d.ckpt", device="cpu").module.net(*inputs)
    R, t = out.R.numpy(), out.t.numpy().reshape(2, 1, 3)
    R_pub, t_pub = np.array(official["3d3d"]["R"]), np.array(official["3d3d"]["t"])
    assert exceeded("rpr.R", absolute(R, R_pub)) or exceeded("rpr.t", absolute(t, t_pub))


def test_a_checkpoint_of_another_configuration_is_refused_naming_the_keys(official, weights, tmp_path):
    from mapfree.rpr import load_method

    src = write_checkpoint(official, "rotbin_trans", weights)
    wrong = tmp_path / "3d3d.ckpt"
    wrong.write_bytes(src.read_bytes())
    with pytest.raises(ValueError, match=r"3d3d\.ckpt: does not match .*head\.mlp"):
        load_method(wrong, device="cpu")
    with pytest.raises(ValueError, match="rpr-<config>"):  # a public checkpoint under an unknown file name
        load_method(_copy(src, tmp_path / "mine.ckpt"), device="cpu")
    bad = tmp_path / "broken.ckpt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"broken.ckpt is refused: text, not weights \(.not a checkpoint.\)"):
        load_method(bad, device="cpu")


def _copy(src: Path, dst: Path) -> Path:
    dst.write_bytes(src.read_bytes())
    return dst


def _public_preprocess(path: Path) -> torch.Tensor:
    """The public code's image reading, written independently: cv2.imread, BGR->RGB, resize to W 270 x H 360."""
    import cv2

    img = cv2.resize(cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB), (270, 360))
    return torch.from_numpy(img).float().permute(2, 0, 1)[None] / 255


def test_relocalize_cli_matches_the_network_on_public_preprocessing(official, weights, realmini, capsys, monkeypatch):
    """``mapfree relocalize REF QUERY --method rpr-3d3d --checkpoint CKPT`` on landscape photos (squashed to
    270×360 as the public code does) prints the network's pose; without --checkpoint the weights come from
    $MAPFREE_WEIGHTS_DIR, and a missing file names itself and the release's address."""
    from mapfree.cli import main
    from mapfree.geometry import Pose
    from mapfree.rpr import load_method

    ckpt = write_checkpoint(official, "3d3d", weights)
    scene = realmini / "val" / "s00000"
    ref, query = scene / "seq0" / "frame_00000.jpg", scene / "seq1" / "frame_00005.jpg"
    net = load_method(ckpt, device="cpu").module.net
    with torch.no_grad():
        out = net(_public_preprocess(ref), _public_preprocess(query))
    want = Pose(out.R[0].double().numpy(), out.t[0].double().numpy())
    capsys.readouterr()
    assert (
        main(
            ["relocalize", str(ref), str(query), "--method", "rpr-3d3d", "--checkpoint", str(ckpt), "--gt-pose", "auto"]
        )
        == 0
    )
    res = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(np.array(res["R"]), want.R, atol=1e-5)
    np.testing.assert_allclose(np.array(res["t"]), want.t, atol=1e-5)
    np.testing.assert_allclose(Pose.from_qt(res["q_wxyz"], res["t"]).R, want.R, atol=1e-5)
    assert res["confidence"] == 0.0 and "error" in res  # the published models carry no confidence
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(weights))
    from mapfree.methods import get

    found = get("rpr-3d3d").build().module.net.state_dict()  # no --checkpoint: $MAPFREE_WEIGHTS_DIR/3d3d.ckpt
    assert all(torch.equal(v, net.state_dict()[k]) for k, v in found.items())
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(weights / "empty"))
    assert main(["relocalize", str(ref), str(query), "--method", "rpr-rot6d_trans"]) == 1
    err = capsys.readouterr().err
    assert "'rot6d_trans.ckpt' not found" in err and "mapfree_rpr_weights.zip" in err


@pytest.mark.slow
def test_run_split_with_a_published_model_writes_the_networks_poses(official, weights, realmini, tmp_path, capsys):
    """``mapfree run ROOT --method rpr-3d3d --checkpoint CKPT``: every scored query's pose is the network's on the
    public preprocessing, with confidence 0 (the published models carry none)."""
    import zipfile

    from mapfree.cli import main
    from mapfree.data import Dataset
    from mapfree.geometry import Pose
    from mapfree.rpr import load_method

    ckpt = write_checkpoint(official, "3d3d", weights)
    out = tmp_path / "sub.zip"
    assert (
        main(
            [
                "run",
                str(realmini),
                "--split",
                "val",
                "--scenes",
                "s00003",
                "--method",
                "rpr-3d3d",
                "--checkpoint",
                str(ckpt),
                "-o",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    capsys.readouterr()
    rows = [r.split() for r in zipfile.ZipFile(out).read("pose_s00003.txt").decode().splitlines() if r.strip()]
    scene = Dataset(realmini).scene("val", "s00003")
    assert [r[0] for r in rows] == [q.name for q in scene.scored_queries()]
    assert all(float(r[8]) == 0.0 for r in rows)
    net = load_method(ckpt, device="cpu").module.net
    last = rows[-1]  # one pair recomputed independently (the others go through the same code)
    with torch.no_grad():
        o = net(_public_preprocess(scene.reference.image_path), _public_preprocess(scene.frame(last[0]).image_path))
    got = Pose.from_qt(np.array(last[1:5], float), np.array(last[5:8], float))
    np.testing.assert_allclose(got.R, o.R[0].double().numpy(), atol=1e-5)
    np.testing.assert_allclose(got.t, o.t[0].double().numpy(), atol=1e-5)


@pytest.mark.slow
def test_finetune_a_confidence_on_top_of_a_published_model(official, weights, tmp_path):
    """``mapfree train 3d3d --init 3d3d.ckpt --freeze pose --set model.uncertainty=true``: only the added
    uncertainty head trains (frozen encoder features cached); the poses stay the published model's exactly and
    the submissions gain a confidence."""
    import pytorch_lightning as pl

    from mapfree.cli import main
    from mapfree.rpr import load_method
    from mapfree.rpr.config import apply_overrides, load_config, resolve_config
    from mapfree.rpr.module import RPRModule
    from test_rpr_train import make_tiny_root

    root = make_tiny_root(tmp_path / "data", n_train=1, frames=3)
    ckpt = write_checkpoint(official, "3d3d", weights)
    sets = [
        "data.pairs_per_scene=2",
        "data.batch_size=2",
        "data.val_batch_size=1",
        "data.max_val_pairs=1",
        "model.uncertainty=true",
        "train.cache_features=true",
    ]
    out = tmp_path / "ft"
    args = [
        "train",
        "3d3d",
        "--data",
        str(root),
        "--out",
        str(out),
        "--init",
        str(ckpt),
        "--freeze",
        "pose",
        "--max-steps",
        "2",
        "--accelerator",
        "cpu",
        "--devices",
        "1",
        "--no-progress",
    ]
    assert main(args + [a for s in sets for a in ("--set", s)]) == 0
    tuned = load_method(out / "checkpoints" / "last.ckpt", device="cpu")
    public = load_method(ckpt, device="cpu").module.state_dict()
    state = tuned.module.state_dict()
    for k, v in public.items():  # weights and BatchNorm statistics untouched
        assert torch.equal(state[k], v), k
    # The uncertainty head moved away from its initialisation (fit seeds with train.seed before building).
    cfg = apply_overrides(load_config(resolve_config("3d3d")), sets + [f"data.root={root}", "train.freeze=pose"])
    pl.seed_everything(cfg.train.seed, verbose=False)
    init = RPRModule(cfg).state_dict()
    assert any(not torch.equal(state[k], init[k]) for k in state if k.startswith("net.uncertainty."))
    x0, x1 = (torch.rand(2, 3, 360, 270, generator=torch.Generator().manual_seed(i)) for i in (1, 2))
    res = tuned.predict({"img0": x0, "img1": x1})
    assert np.isfinite(res["log_sigma"]).all() and ((res["confidence"] > 0) & (res["confidence"] <= 1)).all()
    with pytest.raises(SystemExit):
        main(["train", "3d3d", "--freeze", "bogus"])
    # --freeze pose without an uncertainty head would train nothing: refused before any work.
    assert main(["train", "3d3d", "--data", str(root), "--out", str(tmp_path / "x"), "--freeze", "pose"]) == 1


def test_registering_the_published_methods_does_not_load_torch():
    """``methods.get`` imports ``mapfree.rpr`` to register ``rpr-<config>``: that must stay cheap (no torch,
    ~2 s) for every CLI call and service start, whatever method they ask for."""
    import subprocess
    import sys

    code = (
        "import sys, mapfree.methods as m; m.get('sift_emat_none'); assert m.get('rpr-3d3d').options == "
        "{'config': '3d3d'}; print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"

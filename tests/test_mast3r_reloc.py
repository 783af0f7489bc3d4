"""MASt3R/DUSt3R as mapfree methods on real photos, with tiny fill-rule checkpoints in a temporary
``$MAPFREE_WEIGHTS_DIR``: random weights give junk poses, so these check the plumbing (matches in original
pixels, depth maps at the image size, one forward pass per pair, the reference encoded once, clear errors)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cli_support import mapfree_process
from mapfree import methods
from mapfree.data import Dataset
from mapfree.depth.mast3r import Mast3rDepth
from mapfree.estimate import Estimate
from mapfree.mast3r.checkpoint import PUBLISHED
from mapfree.mast3r.config import config_from_kwargs, parse_constructor
from mapfree.matching import MissingWeightsError
from mapfree.matching.mast3r import Mast3rMatcher
from mapfree.relocalize import Relocalizer
from mapfree_dev.standins.mast3r import save_pth, synthetic_state_dict

QUERIES = ("seq1/frame_00010.jpg", "seq1/frame_00020.jpg")
SMALL = 160  # network input long side for speed (the published models take 512)


@pytest.fixture(scope="module")
def weights(mast3r_fixture, tmp_path_factory):
    """A weights folder holding tiny fill-rule models under the published file names."""
    spec = json.loads((mast3r_fixture / "mast3r.json").read_text())
    root = tmp_path_factory.mktemp("weights")
    for kind in ("mast3r", "dust3r"):
        expr = spec["models"][f"{kind}-tiny"]["expr"]
        sd = synthetic_state_dict(config_from_kwargs(*parse_constructor(expr)))
        save_pth(root / f"{PUBLISHED[kind].stem}.pth", expr, sd)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MAPFREE_WEIGHTS_DIR", str(root))
        yield root


@pytest.fixture(scope="module")
def scene(realmini):
    return Dataset(realmini).scene("val", "s00000")


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    yield


def _check_estimate(est: Estimate, width: int, height: int) -> None:
    assert isinstance(est, Estimate)
    assert est.ok or est.reason  # a pose, or a clean "no estimate" that says why
    m = est.matches
    for k in (m.kpts0, m.kpts1):  # original pixels of these 540x360 photos, not the network's 160x96
        assert np.all(k >= -0.5) and np.all(k[:, 0] <= width - 0.5) and np.all(k[:, 1] <= height - 0.5)
    if len(m):
        assert m.kpts0[:, 0].max() > 160 and np.all(m.scores > 0)  # confidences: exp(.) (+ 1 for points)


@pytest.mark.parametrize(
    "kind, solver, forwards", [("mast3r", "pnp", 1), ("mast3r", "essential", 2), ("dust3r", "pnp", 1)]
)
def test_relocalizer_one_forward_per_pair_reference_encoded_once(weights, scene, kind, solver, forwards, monkeypatch):
    matcher = Mast3rMatcher(kind=kind, long_side=SMALL)
    loc = Relocalizer(matcher, kind, solver)
    assert loc.depth_source.engine is matcher.engine  # the same network serves matches and depth
    engine = matcher.engine
    # a busy engine (a service with many anchors): its image cache keeps nothing useful
    monkeypatch.setattr(engine._images, "size", 1)
    anchor = loc.set_reference(scene.reference)
    assert anchor.depth is None  # pair depth: asked for after matching
    enc0, fwd0 = engine.encodes, engine.forwards
    for q in QUERIES:
        est = loc.localize(scene.frame(q))
        _check_estimate(est, 540, 360)
    assert engine.encodes - enc0 == len(QUERIES)  # each query encodes itself; the reference's output is reused
    # PnP: the pass reference -> query serves matches and reference depth; Ess.Mat adds the symmetric pass
    assert engine.forwards - fwd0 == forwards * len(QUERIES)


def test_pair_depth_at_original_size_from_the_cached_pass(weights, scene):
    matcher = Mast3rMatcher(long_side=SMALL)
    depth = Mast3rDepth(engine=matcher.engine)
    ref, query = scene.reference.image(), scene.frame(QUERIES[0]).image()
    f0, f1 = matcher.extract(ref), matcher.extract(query)
    matcher.match(f0, f1)
    n = matcher.engine.forwards
    d_ref, d_q = depth.pair_depth(ref, query, need_query=False)
    assert matcher.engine.forwards == n and d_q is None  # no second pass for the reference's depth
    assert d_ref.shape == ref.shape[:2] and d_ref.dtype == np.float32
    assert np.all(d_ref >= 0) and np.all(np.isfinite(d_ref))
    # outside the network's crop (540x360 -> 160x107 -> rows 5..100 of 107) there is no depth
    assert not d_ref[:10].any() and not d_ref[-10:].any()
    d_ref2, d_q = depth.pair_depth(ref, query)
    assert matcher.engine.forwards == n + 1 and d_q.shape == query.shape[:2]
    np.testing.assert_array_equal(d_ref, d_ref2)


def test_presets_are_registered_with_what_they_need():
    names = methods.list_methods(depths=())
    for net, file in (
        ("mast3r", "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth"),
        ("dust3r", "DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth"),
    ):
        for solver, name in (("pnp", "pnp"), ("emat", "essential"), ("procrustes", "procrustes")):
            m = methods.get(f"{net}_{solver}_{net}")
            assert f"{net}_{solver}_{net}" in names
            assert (m.matcher, m.depth, m.solver) == (net, net, name) and file in m.description


def test_available_only_with_the_weights(weights, tmp_path, monkeypatch):
    from mapfree import matching

    assert {"mast3r", "dust3r"} <= set(matching.available())
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path))
    assert not {"mast3r", "dust3r"} & set(matching.available())


def test_missing_weights_fail_before_any_work(tmp_path, monkeypatch):
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path))
    with pytest.raises(MissingWeightsError, match="MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth"):
        Relocalizer.from_method("mast3r_pnp_mast3r")


@pytest.mark.slow
def test_cli_relocalize_with_tiny_checkpoint(weights, scene, tmp_path, realmini):
    cfg = tmp_path / "mast3r-small.yaml"
    cfg.write_text(f"extends: mast3r_pnp_mast3r\nmatcher_opts:\n  long_side: {SMALL}\n")
    ref = realmini / "val" / "s00000" / "seq0" / "frame_00000.jpg"
    query = realmini / "val" / "s00000" / QUERIES[0]
    intrinsics = realmini / "val" / "s00000" / "intrinsics.txt"
    r = mapfree_process("relocalize", ref, query, "--method", str(cfg), "--intrinsics", intrinsics)
    assert "Traceback" not in r.stderr, r.stderr
    out = json.loads(r.stdout)
    assert r.returncode == (0 if out["ok"] else 3)  # 3: ran, no estimate
    assert out["method"] == "mast3r-small" and out["scores"]["num_matches"] > 0
    assert out["ok"] or out["reason"]  # junk weights: a pose or a clean no-estimate, never a crash
    r = mapfree_process(
        "relocalize",
        ref,
        query,
        "--method",
        "dust3r_emat_dust3r",
        "--intrinsics",
        intrinsics,
        env={"MAPFREE_WEIGHTS_DIR": str(tmp_path)},
    )
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert "DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth" in r.stderr
    assert "naver/DUSt3R_ViTLarge_BaseDecoder_512_dpt" in r.stderr


@pytest.mark.slow
def test_list_methods_says_what_the_presets_need():
    r = subprocess.run(
        [sys.executable, "-m", "mapfree", "run", "--list-methods"], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    lines = {ln.split()[0]: ln for ln in r.stdout.splitlines() if ln.strip()}
    assert "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth" in lines["mast3r_pnp_mast3r"]
    assert "DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth" in lines["dust3r_emat_dust3r"]
    assert "sift_emat_dptkitti" in lines  # the existing names are still there


def test_service_anchor_cache_keeps_the_encoded_reference(weights, scene, monkeypatch):
    """The service prepares an anchor once per method: later queries encode only themselves."""
    from mapfree.mast3r.engine import shared_engine
    from mapfree.service.anchors.localizers import Localizers, Photo

    monkeypatch.setitem(
        methods._REGISTRY,
        "mast3r-small-test",
        methods.Method(
            name="mast3r-small-test", matcher="mast3r", matcher_opts={"long_side": SMALL}, depth="mast3r", solver="pnp"
        ),
    )
    engine = shared_engine("mast3r", long_side=SMALL)
    locs = Localizers()
    ref = Photo(scene.reference.image(), scene.reference.intrinsics)
    calls = []

    def photos():
        calls.append(1)
        return [ref]

    enc0, fwd0 = engine.encodes, engine.forwards
    for q in QUERIES:
        f = scene.frame(q)
        est = locs.localize_photos("a1", "mast3r-small-test", "v1", photos, f.image(), f.intrinsics)
        _check_estimate(est, 540, 360)
        assert est.extras["method"] == "mast3r-small-test"
    assert len(calls) == 1  # the anchor was prepared once
    assert engine.encodes - enc0 == 1 + len(QUERIES) and engine.forwards - fwd0 == len(QUERIES)
    # Ess.Mat keeps its solver for a plain query photo: the network gives the query's depth (no PnP twin)
    monkeypatch.setitem(
        methods._REGISTRY,
        "mast3r-small-emat",
        methods.Method(
            name="mast3r-small-emat",
            matcher="mast3r",
            matcher_opts={"long_side": SMALL},
            depth="mast3r",
            solver="essential",
        ),
    )
    f = scene.frame(QUERIES[0])
    est = locs.localize_photos("a1", "mast3r-small-emat", "v1", photos, f.image(), f.intrinsics)
    assert est.extras["method"] == "mast3r-small-emat" and "no depth for the query" not in est.reason


def test_batched_pipeline_one_forward_per_pair(weights, scene):
    from mapfree.relocalize.batched import BatchOptions

    matcher = Mast3rMatcher(long_side=SMALL, device="cpu")
    loc = Relocalizer(matcher, "mast3r", "pnp")
    loc.set_reference(scene.reference)
    enc0, fwd0 = matcher.engine.encodes, matcher.engine.forwards
    ests = list(loc.localize_batched([scene.frame(q) for q in QUERIES], options=BatchOptions(batch_size=2)))
    assert len(ests) == len(QUERIES)
    for est in ests:
        _check_estimate(est, 540, 360)
    assert matcher.engine.encodes - enc0 == len(QUERIES) and matcher.engine.forwards - fwd0 == len(QUERIES)


def test_shared_engine_resolves_the_device_as_the_matcher_does(weights):
    """``shared_engine(kind)`` is the engine of a matcher and depth source with the same options, "auto" and
    None included (one engine per network: counters and caches read on it see their passes)."""
    from mapfree.mast3r.engine import shared_engine

    for device in (None, "auto"):
        engine = shared_engine("mast3r", device=device, long_side=SMALL)
        assert Mast3rMatcher(long_side=SMALL, device=device).engine is engine
        assert Mast3rDepth("mast3r", device=device, long_side=SMALL).engine is engine


def test_batched_pairs_equal_pairs_alone(weights, scene):
    """Queries encoded together and decoded as one batch against the reference give each pair what it gets
    alone: the same pointmaps and confidences (to float rounding) and the same matches."""
    ref = scene.reference.image()
    images = [scene.frame(q).image() for q in QUERIES]
    alone = Mast3rMatcher(long_side=SMALL, device="cpu", weights=str(weights / f"{PUBLISHED['mast3r'].stem}.pth"))
    f0 = alone.extract(ref)
    singles = [
        alone.engine.pair(f0.data["encoded"], alone.extract(im).data["encoded"], descriptors=True) for im in images
    ]
    single_matches = [alone.match(f0, alone.extract(im)) for im in images]
    alone.engine._images.size = alone.engine._pairs.size = 0  # nothing cached: the batch computes everything
    feats = alone.extract_many(images)
    enc0, fwd0 = alone.engine.encodes, alone.engine.forwards
    batch = alone.engine.pair_many(f0.data["encoded"], [f.data["encoded"] for f in feats], descriptors=True)
    assert alone.engine.forwards - fwd0 == len(images) and alone.engine.encodes == enc0
    for one, many in zip(singles, batch):
        for key in ("pts1", "conf1", "pts2", "conf2", "desc1", "desc2", "desc_conf1", "desc_conf2"):
            want = getattr(one, key)  # relative to the map's scale: exp() of fill-rule outputs spans decades
            np.testing.assert_allclose(getattr(many, key), want, rtol=1e-4, atol=1e-4 * np.abs(want).max(), err_msg=key)
    for one, many in zip(single_matches, alone.match_many(f0, feats, batch_size=len(feats))):
        assert len(one) > 0
        np.testing.assert_array_equal(many.kpts0, one.kpts0)
        np.testing.assert_array_equal(many.kpts1, one.kpts1)


def test_photos_without_intrinsics_take_the_pointmap_focal(weights, scene, tmp_path, capsys):
    """MASt3R declares the focal estimate (``FocalEstimator``): a photo with neither given intrinsics nor EXIF
    focal tags takes the focal of its own pointmap (within DUSt3R's 0.5-3.5 x a 60° camera, in the photo's own
    pixels), named ``estimated`` in relocalize's JSON, without the default camera's warning."""
    import cv2

    from mapfree.cli import main
    from mapfree.matching.base import FocalEstimator
    from mapfree.relocalize import photo_view

    matcher = Mast3rMatcher(long_side=SMALL)
    assert isinstance(matcher, FocalEstimator)
    ref, query = tmp_path / "a.jpg", tmp_path / "b.jpg"
    for src, dst in ((scene.reference, ref), (scene.frame(QUERIES[0]), query)):
        cv2.imwrite(str(dst), cv2.imread(str(src.image_path)))  # no EXIF, no intrinsics.txt beside it
    v = photo_view(ref, matcher=matcher)
    base = 540 / (2 * np.tan(np.deg2rad(30)))
    assert v.intrinsics_source == "estimated" and 0.99 * 0.5 * base <= v.intrinsics.fx <= 1.01 * 3.5 * base
    assert v.intrinsics.fx == v.intrinsics.fy and (v.intrinsics.cx, v.intrinsics.cy) == (269.5, 179.5)
    assert matcher.estimate_focal(np.full((96, 128, 3), 127, np.uint8)) is None  # a blank photo: none
    cfg = tmp_path / "mast3r-small.yaml"
    cfg.write_text(f"extends: mast3r_pnp_mast3r\nmatcher_opts:\n  long_side: {SMALL}\n")
    rc = main(["relocalize", str(ref), str(query), "--method", str(cfg)])
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert rc in (0, 3) and "warning" not in captured.err
    assert [out["intrinsics"][k]["source"] for k in ("reference", "query")] == ["estimated", "estimated"]
    assert out["intrinsics"]["reference"]["fx"] == pytest.approx(v.intrinsics.fx, rel=0.2)  # paired with the query

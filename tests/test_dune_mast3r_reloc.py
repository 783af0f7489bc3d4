"""DUNE-MASt3R as mapfree methods on real photos, with tiny fill-rule files under the published names in a
temporary ``$MAPFREE_WEIGHTS_DIR`` (the decoder without its encoder: the encoder file is found by the name the
decoder gives). Random weights give junk poses: these check the plumbing (the MASt3R engine shared by matcher and
depth, one forward per pair, the reference encoded once per anchor, the CLI, the listings, clear errors)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cli_support import mapfree_process
from mapfree import matching, methods
from mapfree.data import Dataset
from mapfree.depth.mast3r import Mast3rDepth
from mapfree.estimate import Estimate
from mapfree.mast3r.dune import DuneMast3rModel
from mapfree.mast3r.engine import shared_engine
from mapfree.matching import MissingWeightsError
from mapfree.matching.mast3r import Mast3rMatcher
from mapfree.relocalize import Relocalizer
from mapfree_dev.standins.dune import write_tiny_standin

QUERIES = ("seq1/frame_00010.jpg", "seq1/frame_00020.jpg")
SMALL = 140  # network input long side for speed (the published models take 518)
FILES = {
    "dune-mast3r": ("dunemast3r_cvpr25_vitbase.pth", "dune_vitbase14_448_paper.pth"),
    "dune-mast3r-small": ("dunemast3r_cvpr25_vitsmall.pth", "dune_vitsmall14_448.pth"),
}


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """A weights folder holding the tiny model under the published names of both DUNE-MASt3R files."""
    root = tmp_path_factory.mktemp("weights")
    for kind in FILES:
        write_tiny_standin(root, kind)
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
    assert len(m) > 0
    for k in (m.kpts0, m.kpts1):  # original pixels of these 540x360 photos, not the network's 140x84
        assert np.all(k >= -0.5) and np.all(k[:, 0] <= width - 0.5) and np.all(k[:, 1] <= height - 0.5)
    assert m.kpts0[:, 0].max() > SMALL and np.all(m.scores > 0)


def test_presets_are_registered_with_what_they_need():
    names = methods.list_methods(depths=())
    for net, (decoder, encoder) in FILES.items():
        for solver, name in (("pnp", "pnp"), ("emat", "essential"), ("procrustes", "procrustes")):
            m = methods.get(f"{net}_{solver}_{net}")
            assert f"{net}_{solver}_{net}" in names
            assert (m.matcher, m.depth, m.solver) == (net, net, name)
            assert decoder in m.description and encoder in m.description and "docs/dune-mast3r.md" in m.description


@pytest.mark.parametrize("kind", list(FILES))
def test_relocalizer_one_forward_per_pair_reference_encoded_once(weights, scene, kind):
    """The matcher and the depth source share one engine (the MASt3R one): the reference is encoded once for
    every query, each query once, one decoder pass per pair (PnP), the DUNE network inside."""
    loc = Relocalizer.from_method(
        methods.Method(name=f"{kind}-small", matcher=kind, matcher_opts={"long_side": SMALL}, depth=kind, solver="pnp")
    )
    engine = loc.matcher.engine
    assert isinstance(engine.model, DuneMast3rModel) and loc.depth_source.engine is engine
    loc.set_reference(scene.reference)
    enc0, fwd0 = engine.encodes, engine.forwards
    for q in QUERIES:
        _check_estimate(loc.localize(scene.frame(q)), 540, 360)
    assert engine.encodes - enc0 == len(QUERIES) and engine.forwards - fwd0 == len(QUERIES)


def test_input_is_cropped_to_the_patch_of_14(weights, scene):
    matcher = Mast3rMatcher(kind="dune-mast3r", long_side=SMALL, device="cpu")
    prep = matcher.extract(scene.reference.image()).data["encoded"].prepared
    assert prep.true_shape == (84, 140)  # 540x360 -> 140x93 -> crop to multiples of 14
    assert matcher.engine.long_side == SMALL
    assert shared_engine("dune-mast3r", device="cpu").long_side == 518  # the published size by default


def test_batched_pipeline_one_forward_per_pair(weights, scene):
    from mapfree.relocalize.batched import BatchOptions

    matcher = Mast3rMatcher(kind="dune-mast3r-small", long_side=SMALL, device="cpu")
    loc = Relocalizer(matcher, "dune-mast3r-small", "pnp")
    loc.set_reference(scene.reference)
    enc0, fwd0 = matcher.engine.encodes, matcher.engine.forwards
    ests = list(loc.localize_batched([scene.frame(q) for q in QUERIES], options=BatchOptions(batch_size=2)))
    assert len(ests) == len(QUERIES)
    for est in ests:
        _check_estimate(est, 540, 360)
    assert matcher.engine.encodes - enc0 == len(QUERIES) and matcher.engine.forwards - fwd0 == len(QUERIES)


def test_batched_pairs_equal_pairs_alone(weights, scene):
    ref = scene.reference.image()
    images = [scene.frame(q).image() for q in QUERIES]
    m = Mast3rMatcher(kind="dune-mast3r", long_side=SMALL, device="cpu", weights=str(weights / FILES["dune-mast3r"][0]))
    f0 = m.extract(ref)
    single = [m.match(f0, m.extract(im)) for im in images]
    sizes = m.engine._images.size, m.engine._pairs.size
    m.engine._images.size = m.engine._pairs.size = 0  # nothing cached: the batch computes everything
    try:
        batch = m.match_many(f0, m.extract_many(images), batch_size=len(images))
    finally:  # the engine is shared: later tests count on its caches
        m.engine._images.size, m.engine._pairs.size = sizes
    for one, many in zip(single, batch):
        np.testing.assert_array_equal(one.kpts0, many.kpts0)
        np.testing.assert_array_equal(one.kpts1, many.kpts1)


def test_service_anchor_cache_keeps_the_encoded_reference(weights, scene, monkeypatch):
    """The relocalization service prepares an anchor once per method: later queries encode only themselves."""
    from mapfree.service.anchors.localizers import Localizers, Photo

    monkeypatch.setitem(
        methods._REGISTRY,
        "dune-small-test",
        methods.Method(
            name="dune-small-test",
            matcher="dune-mast3r",
            matcher_opts={"long_side": SMALL},
            depth="dune-mast3r",
            solver="pnp",
        ),
    )
    engine = shared_engine("dune-mast3r", long_side=SMALL)
    locs = Localizers()
    ref = Photo(scene.reference.image(), scene.reference.intrinsics)
    calls = []

    def photos():
        calls.append(1)
        return [ref]

    enc0, fwd0 = engine.encodes, engine.forwards
    for q in QUERIES:
        f = scene.frame(q)
        est = locs.localize_photos("a1", "dune-small-test", "v1", photos, f.image(), f.intrinsics)
        _check_estimate(est, 540, 360)
    assert len(calls) == 1  # the anchor was prepared once
    assert engine.encodes - enc0 == 1 + len(QUERIES) and engine.forwards - fwd0 == len(QUERIES)


def test_depth_source_at_original_size(weights, scene):
    depth = Mast3rDepth("dune-mast3r", long_side=SMALL)
    ref, query = scene.reference, scene.frame(QUERIES[0])
    d_ref, _ = depth.pair_depth(ref.image(), query.image())
    assert d_ref.shape == (360, 540) and d_ref.dtype == np.float32 and np.isfinite(d_ref).all()


def test_available_only_with_both_files(weights, tmp_path, monkeypatch):
    assert set(FILES) <= set(matching.available())
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path))
    (tmp_path / FILES["dune-mast3r"][0]).symlink_to(weights / FILES["dune-mast3r"][0])  # decoder, no encoder
    assert not set(FILES) & set(matching.available())


def test_missing_weights_fail_before_any_work(tmp_path, monkeypatch):
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path))
    with pytest.raises(MissingWeightsError) as e:
        Relocalizer.from_method("dune-mast3r_pnp_dune-mast3r")
    assert "dunemast3r_cvpr25_vitbase.pth" in str(e.value)
    assert "https://download.europe.naverlabs.com/dune/dunemast3r_cvpr25_vitbase.pth" in str(e.value)


def test_cli_relocalize_and_match(weights, tmp_path, realmini):
    cfg = tmp_path / "dune-small.yaml"
    cfg.write_text(f"extends: dune-mast3r-small_pnp_dune-mast3r-small\nmatcher_opts:\n  long_side: {SMALL}\n")
    scene = realmini / "val" / "s00000"
    ref, query, intrinsics = scene / "seq0" / "frame_00000.jpg", scene / QUERIES[0], scene / "intrinsics.txt"
    r = mapfree_process("relocalize", ref, query, "--method", cfg, "--intrinsics", intrinsics)
    assert "Traceback" not in r.stderr, r.stderr
    out = json.loads(r.stdout)
    assert r.returncode == (0 if out["ok"] else 3)  # 3: ran, no estimate
    assert out["method"] == "dune-small" and out["scores"]["num_matches"] > 0 and (out["ok"] or out["reason"])
    r = mapfree_process("match", ref, query, "--matcher", "dune-mast3r", "--size", SMALL, "-o", tmp_path / "m.npz")
    assert r.returncode == 0, r.stderr
    with np.load(tmp_path / "m.npz") as z:
        assert str(z["matcher"]) == "dune-mast3r" and len(z["kpts0"]) > 0 and z["kpts0"][:, 0].max() > SMALL


def test_cli_missing_encoder_and_weights_listing(weights, tmp_path, realmini):
    """A decoder without its encoder file: one line naming the encoder file and its address; ``mapfree
    weights`` lists both files of each matcher with their licence and where they are published."""
    (tmp_path / FILES["dune-mast3r"][0]).symlink_to(weights / FILES["dune-mast3r"][0])
    scene = realmini / "val" / "s00000"
    env = {"MAPFREE_WEIGHTS_DIR": str(tmp_path), "MAPFREE_OFFLINE": "1"}
    r = mapfree_process(
        "relocalize", scene / "seq0" / "frame_00000.jpg", scene / QUERIES[0], "--method",
        "dune-mast3r_pnp_dune-mast3r", "--intrinsics", scene / "intrinsics.txt", env=env,
    )  # fmt: skip
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "dune_vitbase14_448_paper.pth" in lines[0] and "download.europe.naverlabs.com/dune/" in lines[0]
    r = mapfree_process("weights", "dune-mast3r", "dune-mast3r-small", env=env)
    for files in FILES.values():
        for f in files:
            assert f"https://download.europe.naverlabs.com/dune/{f}" in r.stdout or f in r.stdout
    assert (
        "non-commercial" in r.stdout
        and "https://download.europe.naverlabs.com/dune/dune_vitsmall14_448.pth" in r.stdout
    )

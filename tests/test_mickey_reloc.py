"""MicKey as mapfree methods on real photos, with tiny fill-rule weights in a temporary ``$MAPFREE_WEIGHTS_DIR``:
random weights give junk poses, so these check the plumbing (keypoints in original pixels, the keypoints' depth
read back by our solvers, the reference run through the network once, batches, clear errors)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cli_support import mapfree_process
from mapfree import methods
from mapfree.data import Dataset
from mapfree.depth.mickey import MickeyDepth
from mapfree.estimate import Estimate
from mapfree.matching import MissingWeightsError
from mapfree.matching.base import CandidateMatches, Matches
from mapfree.matching.mickey import MickeyMatcher
from mapfree.relocalize import Relocalizer, pipeline
from mapfree.solvers.common import sample_depth_at
from mapfree_dev.standins.mickey import write_standin

QUERIES = ("seq1/frame_00010.jpg", "seq1/frame_00020.jpg")


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    root = write_standin(tmp_path_factory.mktemp("weights"), "tiny")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MAPFREE_WEIGHTS_DIR", str(root))
        mp.setenv("MAPFREE_OFFLINE", "1")
        yield root


@pytest.fixture(scope="module")
def scene(realmini):
    return Dataset(realmini).scene("val", "s00000")


@pytest.fixture(scope="module")
def matcher(weights):
    return MickeyMatcher(device="cpu")


@pytest.fixture(scope="module")
def pair(matcher, scene):
    """The reference and a query, their features and matches (one network pass each)."""
    ref, query = scene.reference, scene.frame(QUERIES[0])
    f0, f1 = matcher.extract(ref.image()), matcher.extract(query.image())
    return ref, query, f0, f1, matcher.match(f0, f1)


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    yield


@pytest.fixture
def solve_always(monkeypatch):
    """Fill-rule weights match each cell with the same cell of the other image, so every pair looks taken from
    the reference's viewpoint and gets the identity pose without a solver: let the solvers run."""
    monkeypatch.setattr(pipeline, "MIN_PARALLAX_PX", -1.0)


def _check_estimate(est: Estimate) -> None:
    assert est.ok or est.reason  # a pose, or a clean "no estimate" that says why
    m = est.matches
    assert len(m) > 0
    for k in (m.kpts0, m.kpts1):  # original pixels of these 540x360 photos (the network's are 540x720)
        assert np.all(k >= -0.5) and np.all(k[:, 0] <= 539.5) and np.all(k[:, 1] <= 359.5)
    assert m.kpts0[:, 1].max() > 180  # spread over the photo, not squeezed into its top half


def test_matches_are_mutual_best_final_scores_in_original_pixels(pair):
    ref, query, f0, f1, m = pair
    assert isinstance(m, CandidateMatches) and len(f0) == len(f1) == 51 * 38
    c = m.candidates
    S = c.scores.numpy()
    assert S.shape == (1938, 1938) and np.all(S >= 0)
    i, j = S.argmax(1), S.argmax(0)
    mutual = np.flatnonzero((j[i] == np.arange(len(i))) & (S.max(1) > 0))
    assert len(m) == len(mutual) > 100
    np.testing.assert_allclose(np.sort(m.scores), np.sort(S[mutual, i[mutual]]), rtol=1e-12)
    assert np.all(np.diff(m.scores) <= 0)  # best first
    # keypoints: the network's (x, y) in its 540x720 input, mapped to the 540x360 photo
    xy_net = f0.data["mickey"].keypoints.xy[0].numpy()
    np.testing.assert_allclose(f0.kpts, np.c_[xy_net[:, 0], (xy_net[:, 1] + 0.5) / 2 - 0.5], atol=1e-4)
    np.testing.assert_allclose(c.kpts0.numpy(), f0.kpts)
    assert set(map(tuple, m.kpts0.round(6))) <= set(map(tuple, f0.kpts.round(6)))


def test_depth_source_gives_each_keypoint_its_depth_back(pair, matcher):
    ref, query, f0, f1, m = pair
    depth = MickeyDepth(engine=matcher.engine)
    n = matcher.engine.images
    d_ref, d_q = depth.pair_depth(ref.image(), query.image(), features=(f0, f1))
    assert matcher.engine.images == n  # read from the features: no network pass
    assert d_ref.shape == (360, 540) and d_ref.dtype == np.float32 and np.all(np.isfinite(d_ref))
    assert 0 < np.count_nonzero(d_ref) <= 1938
    # PnP / Procrustes read the depth at the matched keypoints (nearest pixel): MicKey's own depth comes back
    z = f0.data["mickey"].keypoints.depth[0].numpy()
    idx = [int(np.argmin(np.abs(f0.kpts - k).sum(1))) for k in m.kpts0]
    got = sample_depth_at(d_ref, m.kpts0, ref.intrinsics)
    positive = z[idx] > 0
    assert np.mean(got[positive] == z[idx][positive]) > 0.98  # a few share a pixel with a better-scored one
    assert np.all(got[~positive] == 0)
    # without MicKey features (another matcher's), the source runs the network itself: the same maps
    d_ref2, none = depth.pair_depth(ref.image(), query.image(), need_query=False)
    assert none is None and matcher.engine.images == n + 1
    assert np.array_equal(d_ref2 > 0, d_ref > 0)
    np.testing.assert_allclose(d_ref2, d_ref, rtol=1e-4)  # another thread count: float sums in another order


@pytest.mark.parametrize("name", ["mickey", "mickey_pnp_mickey", "mickey_procrustes_mickey"])
def test_presets_run_against_a_reference_prepared_once(weights, scene, name, solve_always, monkeypatch):
    loc = Relocalizer.from_method(name)
    engine = loc.matcher.engine
    assert loc.depth_source.engine is engine  # the network serves matches and depth
    anchor = loc.set_reference(scene.reference)
    assert anchor.depth is None  # depth comes with the pair's matches
    if name == "mickey":  # no depth maps: MicKey's solver lifts with the depths its candidates carry

        def no_maps(*a, **k):
            raise AssertionError("the mickey solver asked for depth maps")

        monkeypatch.setattr(loc.depth_source, "pair_depth", no_maps)
    n = engine.images
    est = loc.localize(scene.frame(QUERIES[0]))
    _check_estimate(est)
    assert engine.images - n == 1  # the query alone: the reference's output is kept with its features
    if name == "mickey":  # MicKey's own solver and confidence
        assert est.ok and est.extras["n_drawn"] == 2048 and est.confidence == est.extras["confidence_inliers"]


def test_same_viewpoint_shortcut_and_no_matches(weights, scene, pair):
    """Without the override, fill-rule matches do not move: the identity pose, as for any matcher."""
    loc = Relocalizer.from_method("mickey")
    loc.set_reference(scene.reference)
    est = loc.localize(scene.frame(QUERIES[0]))
    assert est.ok and est.extras.get("same_viewpoint") and np.allclose(est.pose.R, np.eye(3))
    from mapfree import solvers

    solver = solvers.create("mickey")
    K = scene.reference.intrinsics
    assert "no matches" in solver.solve(Matches.empty(), K, K, None, None).reason
    plain = pair[4].subset(np.ones(len(pair[4]), bool))  # matches without their candidates
    assert "mickey matcher's scored candidates" in solver.solve(plain, K, K, None, None).reason


def test_batched_pipeline_same_poses_one_network_pass_per_batch(weights, scene, solve_always):
    from mapfree.relocalize.batched import BatchOptions

    loc = Relocalizer("mickey", "mickey", "mickey", solver_opts={"draws": 4})  # fewer draws: a quicker test
    loc.set_reference(scene.reference)
    frames = [scene.frame(q) for q in QUERIES]
    n = loc.matcher.engine.images
    batched = list(loc.localize_batched(frames, options=BatchOptions(batch_size=2, solve_workers=1)))
    assert loc.matcher.engine.images - n == len(QUERIES)
    for est, frame in zip(batched, frames):
        alone = loc.localize(frame)
        _check_estimate(est)
        assert est.ok and alone.ok
        np.testing.assert_allclose(est.pose.R, alone.pose.R, atol=1e-6)  # draws seeded per pair: the same pose
        assert est.confidence == pytest.approx(alone.confidence, rel=1e-5)


def test_service_anchor_keeps_the_reference_output(weights, scene, monkeypatch, solve_always):
    from mapfree.service.anchors.localizers import Localizers, Photo

    monkeypatch.setitem(
        methods._REGISTRY,
        "mickey-quick",
        methods.Method(
            name="mickey-quick", matcher="mickey", depth="mickey", solver="mickey", solver_opts={"draws": 4}
        ),
    )
    locs = Localizers()
    ref = Photo(scene.reference.image(), scene.reference.intrinsics)
    calls = []

    def photos():
        calls.append(1)
        return [ref]

    for q in QUERIES:
        f = scene.frame(q)
        est = locs.localize_photos("a1", "mickey-quick", "v1", photos, f.image(), f.intrinsics)
        _check_estimate(est)
        assert est.ok and est.extras["method"] == "mickey-quick"
    assert len(calls) == 1  # the anchor was prepared once
    f = scene.frame(QUERIES[0])
    est = locs.localize_photos("a1", "mickey_procrustes_mickey", "v1", photos, f.image(), f.intrinsics)
    assert "no depth for the query" not in est.reason  # the keypoints' depth: no PnP fallback needed


def test_presets_listed_with_what_they_need():
    names = methods.list_methods(depths=())
    for name, solver in (
        ("mickey", "mickey"),
        ("mickey_pnp_mickey", "pnp"),
        ("mickey_emat_mickey", "essential"),
        ("mickey_procrustes_mickey", "procrustes"),
    ):
        m = methods.get(name)
        assert name in names and (m.matcher, m.depth, m.solver) == ("mickey", "mickey", solver)
        assert "mickey.ckpt" in m.description and "dinov2_vitl14_pretrain.pth" in m.description
    assert methods.get("mickey_procrustes_mickey").solver_opts["inlier_threshold"] == 0.15
    assert "keypoints" in methods.requirements("mickey")
    problem = methods.depth_free_problem(methods.get("xfeat_pnp_mickey"))
    assert problem and "mickey matcher" in problem
    assert methods.depth_free_problem(methods.get("mickey_emat_sensor")) is None  # MicKey matches, sensor depth


def test_available_only_with_the_weights(weights, tmp_path, monkeypatch):
    from mapfree import matching

    assert "mickey" in matching.available()
    monkeypatch.setenv("MAPFREE_WEIGHTS_DIR", str(tmp_path))
    assert "mickey" not in matching.available()
    with pytest.raises(MissingWeightsError, match="mickey.ckpt"):
        Relocalizer.from_method("mickey")


def test_cli_relocalize_and_match(weights, tmp_path, realmini):
    ref = realmini / "val" / "s00000" / "seq0" / "frame_00000.jpg"
    query = realmini / "val" / "s00000" / QUERIES[0]
    intrinsics = realmini / "val" / "s00000" / "intrinsics.txt"
    env = {"MAPFREE_WEIGHTS_DIR": str(weights), "MAPFREE_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    r = mapfree_process("relocalize", ref, query, "--method", "mickey", "--intrinsics", intrinsics, env=env)
    assert "Traceback" not in r.stderr, r.stderr
    out = json.loads(r.stdout)
    assert r.returncode == 0 and out["ok"] and out["method"] == "mickey" and out["scores"]["num_matches"] > 100
    npz = tmp_path / "m.npz"
    r = mapfree_process("match", ref, query, "--matcher", "mickey", "-o", npz, env=env)
    assert r.returncode == 0, r.stderr
    assert "(1938 / 1938 points)" in r.stdout
    with np.load(npz) as z:
        assert z["kpts0"].shape[0] > 100 and z["kpts0"][:, 1].max() <= 359.5
    r = mapfree_process(
        "relocalize",
        ref,
        query,
        "--method",
        "mickey",
        "--intrinsics",
        intrinsics,
        env={**env, "MAPFREE_WEIGHTS_DIR": str(tmp_path)},
    )
    assert r.returncode == 1 and "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert "mickey.ckpt" in line and "mickey_weights.zip" in line and str(tmp_path / "mickey") in line

"""K reference images by retrieval: DenseVLAD, K-means selection, retrieval, pose triangulation, and
``ReferencedLocalizer`` / ``mapfree run --references K`` on real realmini-dev images."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mapfree.benchmark.metrics import rotation_error_deg, translation_error
from mapfree.data import Dataset
from mapfree.geometry import Pose
from mapfree.retrieval import DenseVLAD, create, dense_rootsift, retrieve, select_references
from mapfree.solvers.triangulation import triangulate_pose
from realmini_layouts import mapfree_multi_reference_scene, realmini_frames

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def hololens(realmini):
    """Every second frame of scene s00000 (real HoloLens images, in time order) and their images."""
    ref, queries = realmini_frames(realmini)
    frames = queries[::2]
    return frames, [f.image() for f in frames]


@pytest.fixture(scope="module")
def vlad(hololens):
    _, images = hololens
    d = create("densevlad")
    return d, d.fit_describe(images)


def errors(est_pose: Pose, gt: Pose) -> tuple[float, float]:
    qe, te = est_pose.qt()
    qg, tg = gt.qt()
    return (
        float(translation_error(qg[None], tg[None], qe[None], te[None])[0]),
        float(rotation_error_deg(qg[None], qe[None])[0]),
    )


def test_dense_rootsift_is_dense_and_root_normalised(hololens):
    desc = dense_rootsift(hololens[1][0])
    assert desc.shape[1] == 128 and len(desc) > 3000  # a grid at 3 patch sizes, not a few keypoints
    assert np.all(desc >= 0)
    np.testing.assert_allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-3)  # sqrt of an L1-normalised histogram


def test_densevlad_unit_vectors_and_temporal_neighbours(hololens, vlad):
    frames, images = hololens
    d, G = vlad
    assert G.shape == (len(images), d.dim) and np.all(np.isfinite(G))
    np.testing.assert_allclose(np.linalg.norm(G, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(d.describe(images[3]), G[3], atol=1e-6)  # describe == fit_describe
    S = G @ G.T
    np.fill_diagonal(S, -np.inf)
    # The most similar other image of a video frame is (nearly always) one of its temporal neighbours.
    near = np.abs(S.argmax(axis=1) - np.arange(len(G))) <= 2
    assert near.mean() >= 0.8
    assert np.all(d.describe(np.zeros((64, 64, 3), np.uint8)) == 0)  # blank: no gradient, no NaN
    with pytest.raises(RuntimeError, match="fit"):
        DenseVLAD().describe(images[0])


def test_select_references_and_retrieve(realmini, vlad):
    d, G = vlad
    keep = select_references(G, 4)
    assert len(keep) == 4 and len(set(keep.tolist())) == 4 and np.all(np.diff(keep) > 0)
    assert np.array_equal(select_references(G, 4), keep)  # seeded: reproducible
    assert np.array_equal(select_references(G, 100), np.arange(len(G)))
    with pytest.raises(ValueError, match=">= 1"):
        select_references(G, 0)
    idx, sim = retrieve(G[keep], G, top=2)
    assert np.array_equal(idx[:, 0], keep) and np.allclose(sim[:, 0], 1.0, atol=1e-5)
    # Two places: K = 2 picks one image of each (TUM office vs HoloLens room, same vocabulary).
    other = [f.image() for f in Dataset(realmini).scene("val", "s00003").queries[:6]]
    G2 = np.vstack([G[:6], d.describe_many(other)])
    two = select_references(G2, 2)
    assert (two < 6).sum() == 1
    with pytest.raises(ValueError, match="dimensions"):
        retrieve(G[0, :10], G)


def test_pose_triangulation_exact_and_degenerate():
    rng = np.random.default_rng(1)
    from scipy.spatial.transform import Rotation

    def pose() -> Pose:
        return Pose(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))

    q, refs = pose(), [pose(), pose()]
    rel = [q @ r.inverse() for r in refs]
    rel = [Pose(p.R, 3.0 * p.t / np.linalg.norm(p.t)) for p in rel]  # only the direction is known
    est = triangulate_pose(refs, rel, [50, 80])
    assert est.ok and est.confidence == 50
    np.testing.assert_allclose(est.pose.R, q.R, atol=1e-9)
    np.testing.assert_allclose(est.pose.t, q.t, atol=1e-9)
    flipped = [Pose(rel[0].R, -rel[0].t), Pose(rel[1].R, -rel[1].t)]
    assert not triangulate_pose(refs, flipped).ok  # rays meeting behind the references
    assert (
        "parallel"
        in triangulate_pose(
            [refs[0], Pose(refs[0].R, refs[0].t + [0, 0, 0.5])], [Pose(np.eye(3), [0, 0, 1.0])] * 2
        ).reason
    )
    assert not triangulate_pose(refs[:1], rel[:1]).ok


@pytest.mark.slow
def test_k_references_retrieve_and_beat_one_reference(realmini):
    from mapfree.relocalize import Relocalizer
    from mapfree.relocalize.references import ReferencedLocalizer

    ref, queries = realmini_frames(realmini)
    mapping, tests = [ref] + queries[0::4], queries[2::4]
    loc = Relocalizer.from_method("sift_pnp_sensor")
    results = {}
    for k in (1, 4):
        bound = ReferencedLocalizer.build(loc, mapping, k=k)
        refs = bound.references
        assert len(refs) == k and set(refs.names) <= {f.name for f in mapping}
        ests = [bound.localize(q) for q in tests]
        ok = [e for e in ests if e.ok]
        assert all(e.extras["reference"] in refs.names for e in ok)
        results[k] = sum(
            1
            for e, q in zip(ests, tests)
            if e.ok and errors(e.pose, q.pose)[0] < 0.25 and errors(e.pose, q.pose)[1] < 5
        )
    assert results[4] == len(tests) and results[4] > results[1]
    assert loc.anchor is None  # binding leaves the localizer as it was: one reference, set as usual
    loc.set_reference(ref)
    assert loc.localize(tests[0]).ok


@pytest.mark.slow
def test_prefetched_path_honours_the_references(realmini, tmp_path):
    """With K references bound, ``localize_many`` (what ``mapfree run`` calls) retrieves per query exactly as
    ``localize`` does (same reference, same pose), with and without prefetching, and a bad query fails the same
    way in all of them."""
    from mapfree.relocalize import Relocalizer
    from mapfree.relocalize.references import ReferencedLocalizer

    ref, queries = realmini_frames(realmini)
    mapping, tests = [ref] + queries[0::4], queries[2::4]
    bound = ReferencedLocalizer.build(Relocalizer.from_method("sift_pnp_sensor"), mapping, k=4)
    refs = bound.references
    items = tests[:2] + [(tmp_path / "missing.jpg", tests[0].intrinsics)] + tests[2:]
    one = [bound.localize(q) for q in items]
    assert sum(e.ok for e in one) == len(tests) and {e.extras["reference"] for e in one if e.ok} - {ref.name}
    for many in (list(bound.localize_many(items, prefetch=2)), list(bound.localize_many(items, prefetch=0))):
        assert len(many) == len(one)
        for a, b in zip(one, many):
            assert (a.ok, a.reason, a.extras.get("reference")) == (b.ok, b.reason, b.extras.get("reference"))
            assert a.pose is None or np.allclose(a.pose.matrix, b.pose.matrix, atol=1e-9)
    assert all(e.extras["reference"] in refs.names for e in one if e.ok)


@pytest.mark.slow
def test_pose_triangulation_on_real_references(realmini):
    from mapfree.relocalize.references import ReferencedLocalizer

    ref, queries = realmini_frames(realmini)
    # A method name: no depth at all, the scale comes from the references.
    bound = ReferencedLocalizer.build("sift_emat_none", [ref] + queries[0::4], k=4, mode="triangulation")
    est = bound.localize(queries[14])
    assert est.ok and len(est.extras["references"].split(",")) == 2
    t_err, r_err = errors(est.pose, queries[14].pose)
    assert t_err < 0.25 and r_err < 5
    with pytest.raises(ValueError, match="K >= 2"):
        ReferencedLocalizer.build(bound.localizer, [ref], k=1, mode="triangulation")


@pytest.mark.slow
def test_run_with_k_references_cli(realmini, tmp_path, capsys):
    from mapfree.cli import main

    root = mapfree_multi_reference_scene(realmini, tmp_path / "data")
    out = tmp_path / "k4.zip"
    rc = main(
        [
            "run",
            str(root),
            "--method",
            "sift_pnp_sensor",
            "--references",
            "4",
            "--all-frames",
            "-o",
            str(out),
            "--no-progress",
            "--evaluate",
            "--json",
        ]
    )
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["estimated"] == 6 and res["metrics"]["Precision @ Pose Error < (25.0cm, 5deg)"] == 1.0
    header, *recs = [json.loads(line) for line in (tmp_path / "k4.journal.jsonl").read_text().splitlines()]
    assert header["method"]["options"]["references"] == {"k": 4, "mode": "retrieval", "top": 1}
    assert all("retrieval_similarity" in r["scores"] for r in recs)
    # A scene with one posed seq0 image cannot triangulate: refused before any work, naming the scene.
    capsys.readouterr()
    rc = main(
        [
            "run",
            str(realmini),
            "--method",
            "sift_emat_none",
            "--references",
            "2",
            "--reference-mode",
            "triangulation",
            "--scenes",
            "s00003",
            "-o",
            str(tmp_path / "tri.zip"),
            "--no-progress",
        ]
    )
    assert rc == 1 and "triangulation needs 2 posed seq0" in capsys.readouterr().err
    assert not (tmp_path / "tri.zip").exists()
    assert (
        main(["run", str(root), "--method", "sift_pnp_sensor", "--references", "0", "-o", str(tmp_path / "bad.zip")])
        == 1
    )

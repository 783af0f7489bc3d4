"""The batched, pipelined path (``Relocalizer.localize_batched``, ``mapfree run --batch``) gives the poses of
``localize`` one pair at a time on real images; batched LightGlue gives each pair its own matches; every learned
network runs with the steady attention kernels (no cuDNN attention)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mapfree.data import Dataset
from mapfree.geometry import rotation_angle_deg
from mapfree.relocalize import Relocalizer
from mapfree.relocalize.batched import BatchOptions

MATCHERS = {  # light settings: a few seconds on 2 cores
    "sift": {},
    "xfeat": {},
    "aliked-lightglue": {"max_keypoints": 512},
}


def _queries(realmini, scene: str, n: int) -> tuple:
    s = Dataset(realmini).scene("val", scene)
    return s.reference, s.queries[3 : 3 + n] + [s.reference]  # the reference itself: the identity pose


def _same(a, b, exact: bool) -> None:
    """Exactly the same estimate, or (a network run on a batch of images instead of one: float rounding in
    the convolutions) the same up to 0.05 degrees, 5 mm and 2 % of the inliers."""
    assert a.ok == b.ok and a.reason == b.reason
    if not a.ok:
        return
    if exact:
        assert a.inliers == b.inliers and a.confidence == pytest.approx(b.confidence)
        assert np.allclose(a.pose.R, b.pose.R, atol=1e-9) and np.allclose(a.pose.t, b.pose.t, atol=1e-9)
    else:
        assert abs(a.inliers - b.inliers) <= max(1, 0.02 * a.inliers)
        assert rotation_angle_deg(a.pose.R, b.pose.R) < 0.05 and np.linalg.norm(a.pose.t - b.pose.t) < 5e-3


@pytest.mark.parametrize("name", list(MATCHERS))
def test_batched_path_equals_one_pair_at_a_time(name, realmini, one_torch_thread):
    loc = Relocalizer(name, "files:sensor", "essential", matcher_opts={"device": "cpu", **MATCHERS[name]})
    for scene, n in (("s00000", 2),) if name == "aliked-lightglue" else (("s00000", 4), ("s00002", 2)):
        ref, queries = _queries(realmini, scene, n)
        anchor = loc.prepare(ref)
        one = [loc.localize(q, anchor) for q in queries]
        many = list(
            loc.localize_batched(
                queries, anchor=anchor, options=BatchOptions(batch_size=3, decode_workers=2, solve_workers=2)
            )
        )
        assert len(many) == len(queries)
        for a, b in zip(one, many):
            _same(a, b, exact=name != "aliked-lightglue")
        assert sum(e.ok for e in many) >= n and many[-1].extras.get("same_viewpoint")
        assert np.allclose(many[-1].pose.R, np.eye(3)) and np.allclose(many[-1].pose.t, 0)
        assert all(set(e.timings) >= {"read", "total"} and all(np.isfinite(list(e.timings.values()))) for e in many)


def test_batched_path_isolates_bad_queries(realmini, tmp_path, one_torch_thread):
    ref, queries = _queries(realmini, "s00000", 2)
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"not a jpeg")
    loc = Relocalizer("xfeat", "files:sensor", "essential", matcher_opts={"device": "cpu"})
    items = [queries[0], (bad, ref.intrinsics.K), queries[1]]
    out = list(loc.localize_batched(items, anchor=loc.prepare(ref), options=BatchOptions(batch_size=4)))
    assert [e.ok for e in out] == [True, False, True] and "broken.jpg" in out[1].reason


def test_batched_lightglue_gives_each_pair_its_own_matches(realmini, one_torch_thread):
    """LightGlue over a padded batch (per-pair early stop and pruning) = kornia's own forward on that pair."""
    from mapfree import matching
    from mapfree.matching.glue import glue_input, run_glue

    m = matching.create("aliked-lightglue", device="cpu", max_keypoints=512)
    ref, queries = _queries(realmini, "s00000", 3)
    f0 = m.extract(ref.image())
    fs = m.extract_many([q.image() for q in queries[:3]])
    batched = run_glue(m.glue, glue_input(f0), [glue_input(f) for f in fs])

    def side(f):
        return {
            "keypoints": f.data["keypoints"][None],
            "descriptors": f.data["descriptors"][None],
            "image_size": torch.tensor([f.data["resized"]], dtype=torch.float32),
        }

    for f1, (idx, scores) in zip(fs, batched):
        with torch.inference_mode():
            ko = m.glue({"image0": side(f0), "image1": side(f1)})
        theirs = ko["matches"][0].numpy()
        assert len(idx) > 50 and sorted(map(tuple, idx.tolist())) == sorted(map(tuple, theirs.tolist()))
        assert np.allclose(np.sort(scores), np.sort(ko["scores"][0].numpy()), atol=1e-4)


def test_learned_networks_never_use_cudnn_attention(realmini, one_torch_thread, monkeypatch):
    """Every attention call of LightGlue and LighterGlue runs with cuDNN attention off (on a GPU it builds a graph
    per new sequence length) and without cuDNN autotuning; outside, the user's settings are untouched."""
    from mapfree import matching

    seen: list[tuple[bool, bool]] = []
    real = torch.nn.functional.scaled_dot_product_attention

    def spy(*args, **kwargs):
        seen.append((torch.backends.cuda.cudnn_sdp_enabled(), torch.backends.cudnn.benchmark))
        return real(*args, **kwargs)

    monkeypatch.setattr(torch.nn.functional, "scaled_dot_product_attention", spy)
    monkeypatch.setattr(torch.backends.cudnn, "benchmark", True)
    ref, queries = _queries(realmini, "s00000", 1)
    for name, opts in (("aliked-lightglue", {"max_keypoints": 256}), ("xfeat-lighterglue", {"top_k": 1024})):
        m = matching.create(name, device="cpu", **opts)
        assert len(m.match(m.extract(ref.image()), m.extract(queries[0].image()))) > 10
    assert len(seen) > 10 and not any(cudnn or bench for cudnn, bench in seen)
    assert torch.backends.cuda.cudnn_sdp_enabled() and torch.backends.cudnn.benchmark


def test_run_split_batched_writes_the_same_submission(realmini, tmp_path, one_torch_thread):
    import zipfile

    from mapfree.relocalize import read_journal, run_split

    outs = {}
    for batch in (0, 4):
        out = tmp_path / f"b{batch}" / "sub.zip"
        res = run_split(realmini, "val", "xfeat_emat_sensor", out, scenes=["s00001"], progress=False, batch_size=batch)
        assert res.computed >= 5 and res.estimated >= 4
        with zipfile.ZipFile(out) as z:
            outs[batch] = z.read("pose_s00001.txt").decode()
        assert [r["frame"] for r in read_journal(res.journal)[1]] == [
            f.name for f in Dataset(realmini).scene("val", "s00001").scored_queries()
        ]
    assert outs[0] == outs[4] and outs[0].count("\n") >= 4


def test_depth_files_are_read_by_the_decode_workers(realmini, monkeypatch, one_torch_thread):
    """A query's depth file is decoded beside its photo in a decode worker, not on the thread that drives the
    device (profiled on a GPU, reading the PNGs there cost a third of each pair's time); the maps are the same."""
    import threading

    from mapfree.depth.files import FileDepth

    readers: list[str] = []
    real = FileDepth.depth

    def recording(self, frame):
        readers.append(threading.current_thread().name)
        return real(self, frame)

    monkeypatch.setattr(FileDepth, "depth", recording)
    loc = Relocalizer("sift", "files:sensor", "essential")
    ref, queries = _queries(realmini, "s00000", 3)
    anchor = loc.prepare(ref)
    readers.clear()
    many = list(
        loc.localize_batched(
            queries, anchor=anchor, options=BatchOptions(batch_size=2, decode_workers=2, solve_workers=1)
        )
    )
    assert len(readers) == len(queries) and all(r.startswith("mapfree-decode") for r in readers)
    for a, b in zip([loc.localize(q, anchor) for q in queries], many):
        _same(a, b, exact=True)

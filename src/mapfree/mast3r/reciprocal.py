"""Fast reciprocal nearest neighbours between two dense descriptor maps (MASt3R's matcher).

Start from a regular grid of pixels in image 1 (every ``subsample`` pixels, offset by half a step); follow
nearest neighbours 1 -> 2 -> 1 until a pixel maps back to itself (a reciprocal pair) or ``max_iter`` rounds
pass. The CPU path uses exact KD-tree searches (L2); the torch path brute-forces the same L2 search in blocks
(on a GPU), or the dot product for unit descriptors.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import KDTree

__all__ = ["reciprocal_matches", "merge_pairs"]


class _TorchNN:
    """Nearest neighbour in ``db`` for batches of queries, by blocks of brute force on ``device``.

    Dot products go through one reused score buffer: with 24-D descriptors the products are cheap and writing
    fresh score matrices (page faults, memory traffic) is what costs."""

    def __init__(self, db: torch.Tensor, dist: str = "l2", block: tuple[int, int] | None = None) -> None:
        # (queries, database rows) per block: 32 MB of scores on the CPU (cache-sized); 512 MB on a GPU, where
        # each block costs kernel launches and a 512x384 map is then searched in six blocks, not 48
        cuda = db.device.type == "cuda"
        self.db, self.dist, self.block = db, dist, block or ((4096, 32768) if cuda else (2048, 4096))

    def _best(self, qb: torch.Tensor, buf: torch.Tensor) -> torch.Tensor:
        best_val: torch.Tensor | None = None
        best_idx: torch.Tensor | None = None
        bd = self.block[1]
        for j in range(0, len(self.db), bd):
            d = self.db[j : j + bd]
            if self.dist == "dot":
                score = buf[: len(qb) * len(d)].view(len(qb), len(d))
                torch.mm(qb, d.T, out=score)
                val, idx = score.max(dim=1)
                val = -val
            else:
                val, idx = torch.cdist(qb, d).min(dim=1)
            idx = idx + j
            if best_val is None or best_idx is None:
                best_val, best_idx = val, idx
            else:
                better = val < best_val  # ties keep the first (lowest) index, as a single argmin would
                best_val = torch.where(better, val, best_val)
                best_idx = torch.where(better, idx, best_idx)
        assert best_idx is not None
        return best_idx

    def query(self, q: np.ndarray | torch.Tensor) -> np.ndarray:
        q = torch.as_tensor(q, device=self.db.device)
        if len(q) == 0:
            return np.zeros(0, dtype=np.int64)
        bq, bd = self.block
        buf = torch.empty(min(bq, len(q)) * bd, dtype=self.db.dtype, device=self.db.device)
        return torch.cat([self._best(q[i : i + bq], buf) for i in range(0, len(q), bq)]).cpu().numpy()


class _TreeNN:
    def __init__(self, db: np.ndarray) -> None:
        self.db = db
        self.tree = KDTree(db)

    def query(self, q: np.ndarray | torch.Tensor) -> np.ndarray:
        return self.tree.query(np.asarray(q))[1]


def _rows(points: np.ndarray | torch.Tensor, idx: np.ndarray) -> np.ndarray | torch.Tensor:
    return points[torch.as_tensor(idx).long()] if isinstance(points, torch.Tensor) else points[idx]


def merge_pairs(idx1: np.ndarray, idx2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique index pairs, sorted by ``idx1`` then ``idx2``.

    Args:
        idx1: (N,) non-negative indices below 2**32.
        idx2: (N,) non-negative indices below 2**32.

    Returns:
        (M,) int64 ``idx1`` and (M,) int64 ``idx2`` of the distinct pairs.
    """
    key = np.unique((idx1.astype(np.int64) << 32) | idx2.astype(np.int64))
    return (key >> 32).astype(np.int64), (key & 0xFFFFFFFF).astype(np.int64)


def reciprocal_matches(
    desc1: np.ndarray | torch.Tensor,
    desc2: np.ndarray | torch.Tensor,
    subsample: int = 8,
    device: str | torch.device = "cpu",
    dist: str = "l2",
    max_iter: int = 10,
    brute_force: bool | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Reciprocal nearest-neighbour matches between two dense descriptor maps (MASt3R's fast matcher).

    Args:
        desc1: (H1, W1, D) descriptors of image 1.
        desc2: (H2, W2, D) descriptors of image 2.
        subsample: Grid step of the starting pixels in image 1.
        device: Where brute force runs.
        dist: ``l2``, or ``dot`` for unit descriptors (brute force only).
        max_iter: Rounds of 1 -> 2 -> 1 before giving up on the pixels still moving.
        brute_force: Blocks of brute force even on the CPU; None: KD-trees on the CPU with ``l2`` (the public
            CPU path), brute force elsewhere.

    Returns:
        (N, 2) integer (x, y) pixels in image 1 and (N, 2) in image 2, sorted by the pixel index in image 1.

    Raises:
        ValueError: The descriptor widths differ.
    """
    h1, w1, dim = desc1.shape
    h2, w2, dim2 = desc2.shape
    if dim != dim2:
        raise ValueError(f"descriptor widths differ: {dim} vs {dim2}")
    s = int(subsample)
    ys, xs = np.mgrid[s // 2 : h1 : s, s // 2 : w1 : s].reshape(2, -1)
    xy1 = np.unique(xs + w1 * ys).astype(np.int32)
    xy2 = np.full_like(xy1, -1)
    old1, old2 = xy1.copy(), xy2.copy()
    if brute_force is None:
        brute_force = torch.device(device).type != "cpu" or dist != "l2"
    p1: np.ndarray | torch.Tensor
    p2: np.ndarray | torch.Tensor
    nn1: _TreeNN | _TorchNN
    nn2: _TreeNN | _TorchNN
    if not brute_force:
        p1 = np.asarray(torch.as_tensor(desc1).detach().cpu()).reshape(-1, dim)
        p2 = np.asarray(torch.as_tensor(desc2).detach().cpu()).reshape(-1, dim)
        nn1, nn2 = _TreeNN(p1), _TreeNN(p2)
    else:
        p1 = torch.as_tensor(desc1).to(device).reshape(-1, dim)
        p2 = torch.as_tensor(desc2).to(device).reshape(-1, dim)
        nn1, nn2 = _TorchNN(p1, dist), _TorchNN(p2, dist)
    moving = np.ones(len(xy1), dtype=np.bool_)
    for _ in range(max_iter):
        if not moving.any():
            break
        xy2[moving] = nn2.query(_rows(p1, xy1[moving]))
        moving &= old2 != xy2
        xy1[moving] = nn1.query(_rows(p2, xy2[moving]))
        moving &= old1 != xy1
        old2[:] = xy2
        old1[:] = xy1
    i1, i2 = merge_pairs(xy1[~moving], xy2[~moving])
    return np.stack([i1 % w1, i1 // w1], axis=1), np.stack([i2 % w2, i2 // w2], axis=1)

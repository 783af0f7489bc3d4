"""Overlaps of a built scene as the paper defines them: shared SfM points / max(points seen in either frame)."""

from __future__ import annotations

import numpy as np
from scipy import sparse

from ..data.overlaps import Overlaps

__all__ = ["sfm_overlaps"]


def sfm_overlaps(point_ids: list[np.ndarray], seq: np.ndarray, number: np.ndarray) -> Overlaps:
    """Every ordered pair of distinct frames sharing a 3D point, within and across scans.

    ``point_ids[i]`` are the SfM points frame i observes. Sparse (frames x points) incidence, so a scene of
    thousands of frames and a million points costs one sparse product.
    """
    sets = [np.unique(p) for p in point_ids]
    rows = np.repeat(np.arange(len(sets)), [len(s) for s in sets])
    cols = np.concatenate(sets) if sets else np.zeros(0, np.int64)
    _, cols = np.unique(cols, return_inverse=True)
    V = sparse.csr_matrix((np.ones(len(rows), np.float32), (rows, cols.ravel())),
                          shape=(len(sets), int(cols.max()) + 1 if len(cols) else 0))
    shared = (V @ V.T).tocoo()
    n = np.array([len(s) for s in sets], np.float64)
    keep = shared.row != shared.col
    a, b, common = shared.row[keep], shared.col[keep], shared.data[keep]
    order = np.lexsort((b, a))
    a, b, common = a[order], b[order], common[order]
    seq, number = np.asarray(seq), np.asarray(number)
    idxs = np.stack([seq[a], number[a], seq[b], number[b]], 1).astype(np.int64).reshape(-1, 4)
    return Overlaps(idxs, common / np.maximum(np.maximum(n[a], n[b]), 1))

"""Choosing K representative images of a place (K-means over global descriptors) and retrieving among them."""

from __future__ import annotations

import numpy as np

__all__ = ["select_references", "retrieve"]


def _unit_rows(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or not np.all(np.isfinite(x)):
        raise ValueError(f"descriptors must be a finite (N, D) array, got shape {x.shape}")
    n = np.linalg.norm(x, axis=1, keepdims=True)
    return np.divide(x, n, out=np.zeros_like(x), where=n > 0)


def select_references(descriptors: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """Indices (sorted) of the ``k`` most representative rows: K-means on the unit descriptors, then for each
    cluster the member closest to its centre (paper §5.1). Every row when ``k >= N``."""
    if k < 1:
        raise ValueError(f"the number of references must be >= 1, got {k}")
    x = _unit_rows(descriptors)
    n = len(x)
    if n == 0:
        raise ValueError("no mapping images to choose references from")
    if k >= n:
        return np.arange(n)
    from sklearn.cluster import KMeans

    km = KMeans(n_clusters=k, n_init=4, random_state=seed).fit(x)
    dist = ((x[:, None, :] - km.cluster_centers_[None]) ** 2).sum(-1)  # (N, k)
    chosen = []
    for c in range(k):
        members = np.flatnonzero(km.labels_ == c)
        if len(members):
            chosen.append(int(members[np.argmin(dist[members, c])]))
    # K-means can merge identical images into fewer clusters: fill up with the rows farthest from the chosen.
    while len(set(chosen)) < k:
        d = ((x[:, None, :] - x[chosen][None]) ** 2).sum(-1).min(axis=1)
        d[chosen] = -1
        chosen.append(int(np.argmax(d)))
    return np.array(sorted(set(chosen)))


def retrieve(query: np.ndarray, database: np.ndarray, top: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The ``top`` most similar database rows for each query (cosine similarity, best first).

    ``query`` (D,) or (M,D), ``database`` (N,D) -> indices and similarities, (top,) or (M,top).
    """
    single = np.ndim(query) == 1
    q = _unit_rows(np.atleast_2d(query))
    db = _unit_rows(database)
    if len(db) == 0:
        raise ValueError("empty retrieval database")
    if q.shape[1] != db.shape[1]:
        raise ValueError(f"query descriptors have {q.shape[1]} dimensions, the database {db.shape[1]}")
    sim = q @ db.T
    top = max(1, min(top, len(db)))
    idx = np.argsort(-sim, axis=1, kind="stable")[:, :top]
    best = np.take_along_axis(sim, idx, axis=1)
    return (idx[0], best[0]) if single else (idx, best)

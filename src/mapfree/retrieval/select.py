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
    """Choose the ``k`` most representative images of a place as references, as the paper does.

    K-means on the unit descriptors, then for each cluster the member closest to its centre.

    Args:
        descriptors: (N, D) global descriptors of the mapping images.
        k: Number of references.
        seed: Seed of K-means.

    Returns:
        (min(k, N),) sorted row indices.

    Raises:
        ValueError: ``k < 1``, no row, or the descriptors are not a finite (N, D) array.
    """
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
    """The most similar database rows of each query by cosine similarity, best first.

    Args:
        query: (D,) or (M, D) query descriptors.
        database: (N, D) descriptors to search.
        top: Rows returned per query (at most N).

    Returns:
        Row indices and similarities, each (top,) for one query or (M, top).

    Raises:
        ValueError: The database is empty, the widths differ, or a descriptor is not finite.
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

"""Max-consensus vote over 1-D scale hypotheses, exact and O(n log n).

Hypothesis ``i`` collects the votes ``count_i = #{j : |s_j - s_i| < threshold}`` (itself included); the
winner is the hypothesis with the most votes, ties going to the **first in input order** — what the
paper's loop (``if votes > best: best = ...``) picks. Instead of that O(n²) loop we sort once and find
every window's ends with ``searchsorted`` (O(n log n)); because ``s_i ± threshold`` is rounded, the ends
are then corrected with the very same floating-point predicate ``abs(s_j - s_i) < threshold`` the loop
uses (it is monotone along the sorted order), so the counts equal the loop's bit for bit, duplicates and
values exactly one threshold apart included.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ScaleVote", "scale_vote", "scale_vote_bruteforce", "vote_counts"]


class ScaleVote(tuple):
    """``(index, votes, counts)``: winner's input index (-1 when there is none), its votes, all counts."""

    __slots__ = ()

    def __new__(cls, index: int, votes: int, counts: np.ndarray) -> ScaleVote:
        return super().__new__(cls, (index, votes, counts))

    @property
    def index(self) -> int:  # type: ignore[override]  # the winner's index, not tuple.index: it unpacks as a triple
        """The winner's input index (-1 when there is none)."""
        return self[0]

    @property
    def votes(self) -> int:
        """The winner's number of votes."""
        return self[1]

    @property
    def counts(self) -> np.ndarray:
        """(N,) every hypothesis's number of votes."""
        return self[2]


def vote_counts(s: np.ndarray, threshold: float) -> np.ndarray:
    """Votes of every hypothesis: ``count_i = #{j : |s_j - s_i| < threshold}`` (itself included).

    Args:
        s: (N,) scale hypotheses, metres.
        threshold: Vote radius, metres.

    Returns:
        (N,) int64 counts, 0 for non-finite hypotheses (all 0 for a threshold that is not > 0).
    """
    s = np.asarray(s, dtype=np.float64).reshape(-1)
    counts = np.zeros(len(s), dtype=np.int64)
    finite = np.isfinite(s)
    if not np.any(finite) or not threshold > 0:
        return counts
    v = s[finite]
    a = np.sort(v)
    n = len(a)
    with np.errstate(over="ignore", invalid="ignore"):
        # Window ends from searchsorted; ``v ± threshold`` is rounded, so the ends may be off by the
        # few values within an ulp of the boundary. Fix them with the exact predicate below, moving
        # one run of equal values at a time (searchsorted again), so duplicates cost nothing extra.
        lo = np.searchsorted(a, v - threshold, side="right")
        hi = np.searchsorted(a, v + threshold, side="left")

        def inside(k: np.ndarray) -> np.ndarray:
            return np.abs(a[np.clip(k, 0, n - 1)] - v) < threshold

        while True:  # left end: grow while the element before it is inside, shrink while it is outside
            grow = (lo > 0) & inside(lo - 1)
            shrink = ~grow & (lo < n) & ~inside(lo)
            if not (grow.any() or shrink.any()):
                break
            lo = np.where(grow, np.searchsorted(a, a[np.clip(lo - 1, 0, n - 1)], side="left"), lo)
            lo = np.where(shrink, np.searchsorted(a, a[np.clip(lo, 0, n - 1)], side="right"), lo)
        while True:  # right end (exclusive), mirrored
            grow = (hi < n) & inside(hi)
            shrink = ~grow & (hi > 0) & ~inside(hi - 1)
            if not (grow.any() or shrink.any()):
                break
            hi = np.where(grow, np.searchsorted(a, a[np.clip(hi, 0, n - 1)], side="right"), hi)
            hi = np.where(shrink, np.searchsorted(a, a[np.clip(hi - 1, 0, n - 1)], side="left"), hi)
    counts[finite] = hi - lo
    return counts


def scale_vote(s: np.ndarray, threshold: float) -> ScaleVote:
    """Max-consensus winner of the hypotheses (see the module docstring), in O(n log n).

    Args:
        s: (N,) scale hypotheses, metres.
        threshold: Vote radius, metres.

    Returns:
        ``ScaleVote(index, votes, counts)``: index -1 when there is no finite hypothesis; ties go to the first.
    """
    counts = vote_counts(s, threshold)
    if len(counts) == 0 or counts.max() == 0:
        return ScaleVote(-1, 0, counts)
    i = int(np.argmax(counts))  # argmax returns the first maximum: the loop's tie rule
    return ScaleVote(i, int(counts[i]), counts)


def scale_vote_bruteforce(s: np.ndarray, threshold: float) -> ScaleVote:
    """The paper's O(n²) loop, kept as the reference the fast vote is tested against.

    Args:
        s: (N,) scale hypotheses, metres.
        threshold: Vote radius, metres.

    Returns:
        The same ``ScaleVote`` as ``scale_vote``.
    """
    s = np.asarray(s, dtype=np.float64).reshape(-1)
    best, best_i = 0, -1
    counts = np.zeros(len(s), dtype=np.int64)
    for i, h in enumerate(s):
        with np.errstate(invalid="ignore"):
            c = int(np.sum(np.abs(s - h) < threshold))
        counts[i] = c
        if c > best:
            best, best_i = c, i
    return ScaleVote(best_i, best, counts)

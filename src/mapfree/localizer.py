"""The localizer interfaces: what every method kind builds, and what a run calls.

``QueryLocalizer`` answers queries against the reference(s) it holds: ``localize(query)``, with ``localize_many``
and ``localize_batched`` looping over it unless the localizer has faster forms. ``Localizer`` (what
``Method.build()`` returns: matching pipelines (``mapfree.relocalize.Relocalizer``) and regression networks
(``mapfree.rpr.RPRMethod``) alike) adds the reference: ``set_reference``, ``prepare`` (a reusable anchor),
``localize(query, anchor)`` and ``relocalize(ref, query)``.

A query or a reference is whatever the localizer reads (``ViewLike``): a ``View``, a dataset ``Frame`` or
``(image | path, intrinsics[, depth])`` (``mapfree.data.view.as_view``). This module sits on the ground floor so
that every method kind can derive from it.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import partial
from typing import Any, Generic, TypeVar, cast

from .data.view import ViewLike
from .estimate import Estimate

log = logging.getLogger(__name__)

__all__ = ["QueryLocalizer", "Localizer", "BatchOptions", "error_reason"]

AnchorT = TypeVar("AnchorT")


@dataclass
class BatchOptions:
    """How a batched path (``localize_batched``) cuts and overlaps its work.

    Attributes:
        batch_size: Queries per device pass.
        decode_workers: Threads that read query images and depth files ahead.
        solve_workers: Threads that run the solvers (None: the cores, at most 8).
        ahead: How many batches are decoded ahead.
    """

    batch_size: int = 16
    decode_workers: int = 4
    solve_workers: int | None = None
    ahead: int = 2


def error_reason(e: Exception) -> str:
    """The "no estimate" reason of an exception raised for one query (logged as a warning).

    Args:
        e: The exception.

    Returns:
        ``"error: Type: message"``.
    """
    log.warning("relocalization failed: %s", e, exc_info=log.isEnabledFor(logging.DEBUG))
    return f"error: {type(e).__name__}: {e}"


def _each(localize: Callable[[ViewLike], Estimate], queries: Iterable[ViewLike]) -> Iterator[Estimate]:
    """``localize(query)`` for each query, in order; one that raises is a failed estimate, not the end of a run."""
    for query in queries:
        try:
            yield localize(query)
        except Exception as e:
            yield Estimate.failure(error_reason(e))


class QueryLocalizer(ABC):
    """Answers queries: the pose of a query image relative to the reference(s) it holds."""

    @abstractmethod
    def localize(self, query: ViewLike) -> Estimate:
        """The pose of one query.

        Args:
            query: A ``View``, a ``Frame`` or ``(image | path, K[, depth])`` (see ``as_view``).

        Returns:
            The estimate; ``pose`` None with a ``reason`` when there is none.
        """

    def localize_many(self, queries: Iterable[ViewLike], *, prefetch: int = 1) -> Iterable[Estimate]:
        """``localize`` over many queries, in order; a query that raises is a failed estimate.

        Args:
            queries: The queries.
            prefetch: How many of the next queries are decoded ahead in a background thread, where the localizer
                supports it (0: none).

        Returns:
            One estimate per query.
        """
        return _each(self.localize, queries)

    def localize_batched(
        self, queries: Iterable[ViewLike], *, options: BatchOptions | None = None
    ) -> Iterable[Estimate]:
        """``localize`` over many queries through the localizer's batched device path, when it has one (else
        ``localize_many``).

        Args:
            queries: The queries.
            options: Batch size and threads.

        Returns:
            One estimate per query, in order, each as ``localize`` gives it.
        """
        return self.localize_many(queries)

    def default_batch_size(self) -> int:
        """Queries per device pass when a run leaves it open (``mapfree run`` without ``--batch``).

        Returns:
            0: one query at a time (``localize_many``); a matching method on a GPU says 16.
        """
        return 0

    def check_available(self) -> None:  # noqa: B027 - an optional hook, a no-op unless overridden
        """Raise now, with one clear message, what would make every query fail (a depth network that is neither
        on this machine nor downloadable); nothing to check by default."""


class Localizer(QueryLocalizer, Generic[AnchorT]):
    """What every method kind builds (``Method.build()``): a one-reference localizer.

    ``set_reference(ref)`` then ``localize(query)`` for many queries against one reference; ``prepare(ref)`` makes a
    reusable anchor without making it the current reference (a service keeps many), ``localize(query, anchor)``
    uses it; ``relocalize(ref, query)`` for one pair. ``AnchorT`` is what ``prepare`` returns.
    """

    @abstractmethod
    def set_reference(self, reference: Any) -> AnchorT:
        """Make ``reference`` the one ``localize(query)`` answers against.

        Args:
            reference: A ``ViewLike``, or an anchor from ``prepare``.

        Returns:
            Its anchor.
        """

    @abstractmethod
    def localize(self, query: ViewLike, anchor: AnchorT | None = None) -> Estimate:
        """The pose of ``query`` relative to ``anchor`` (default: the current reference).

        Args:
            query: A ``ViewLike``.
            anchor: An anchor from ``prepare``, or None.

        Returns:
            The estimate (never raises for bad pixels or geometry: ``pose`` is then None, with a reason).
        """

    def prepare(self, reference: Any) -> AnchorT:
        """An anchor of ``reference`` for ``localize(query, anchor)``, without making it the current reference.

        The default keeps the reference itself (a method with nothing to reuse: ``localize`` sets it again).

        Args:
            reference: A ``ViewLike``.

        Returns:
            The anchor.
        """
        return cast(AnchorT, reference)

    def relocalize(self, reference: Any, query: ViewLike) -> Estimate:
        """The pose of ``query`` relative to ``reference``, one pair.

        Args:
            reference: A ``ViewLike``.
            query: A ``ViewLike``.

        Returns:
            The estimate (``X_query = R X_ref + t``, metres).
        """
        return self.localize(query, self.prepare(reference))

    def localize_many(
        self, queries: Iterable[ViewLike], anchor: AnchorT | None = None, *, prefetch: int = 1
    ) -> Iterable[Estimate]:
        """``localize`` over many queries against one anchor, in order; a query that raises is a failed estimate.

        Args:
            queries: The queries.
            anchor: An anchor from ``prepare`` (default: the current reference).
            prefetch: Queries decoded ahead in a background thread, where supported.

        Returns:
            One estimate per query.
        """
        return _each(partial(self.localize, anchor=anchor), queries)

    def localize_batched(
        self, queries: Iterable[ViewLike], *, anchor: AnchorT | None = None, options: BatchOptions | None = None
    ) -> Iterable[Estimate]:
        """``localize_many`` unless the localizer has a batched device path.

        Args:
            queries: The queries.
            anchor: An anchor from ``prepare`` (default: the current reference).
            options: Batch size and threads.

        Returns:
            One estimate per query, in order.
        """
        return self.localize_many(queries, anchor)

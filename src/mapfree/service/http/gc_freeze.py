"""Short garbage-collector pauses in serving processes. A full cyclic collection walks every tracked object
with the GIL held: ~100k after the app is built (60 ms on a 2-core machine), ~250k once torch and a
relocalizer are loaded (~150 ms), and the request churn of large uploads triggers such collections; the
slowest ``/health`` answers during uploads were these pauses. Freezing the long-lived objects (``gc.freeze``)
takes them out of every later collection."""

from __future__ import annotations

import gc

_enabled = False


def freeze_long_lived() -> None:
    """Freeze what is alive now and keep doing so after each heavy load (``after_load``). Call once in a serving
    process, after the app is built; tests and libraries do not, so their processes collect as usual."""
    global _enabled
    _enabled = True
    gc.collect()
    gc.freeze()


def after_load() -> None:
    """A large, long-lived structure (a relocalizer and its model) was just built: freeze it too, in a serving
    process only."""
    if _enabled:
        gc.freeze()


def after_unload() -> None:
    """Long-lived structures were dropped (an evicted relocalizer): frozen objects are never collected, so thaw,
    collect what is garbage now, and freeze the rest again, in a serving process only."""
    if _enabled:
        gc.unfreeze()
        gc.collect()
        gc.freeze()

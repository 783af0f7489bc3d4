"""Built relocalizers of one API process: a pool bounded in bytes, shared by equal configurations.

Each method name used to build and keep up to two relocalizers for the process's life (+46 MB per new name,
and the preset pattern accepts endless names). Here instances are keyed by their *configuration* (the
``Method`` without its name and description; every ``files:`` depth is the uploaded map in the service, so
``sift_pnp_sensor`` and ``sift_pnp_mono`` share one), at most ``per_config`` of each exist, and idle ones of
the least recently used configurations are dropped while the pool holds more than ``max_bytes`` (measured by
walking what each instance keeps, ``prepared.deep_nbytes``). Instances in use are never dropped; a request
for a configuration whose instances are all busy waits for one."""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from ..http.gc_freeze import after_load, after_unload
from .prepared import deep_nbytes


def config_key(method: Any) -> str:
    """What makes two methods build the same relocalizer in the service: everything but the name and
    description, with any depth-file suffix the same (the service's depth is the uploaded map)."""
    depth = "files:" if method.depth.startswith("files:") else method.depth
    return json.dumps(asdict(replace(method, name="", description="", depth=depth)), sort_keys=True, default=str)


@dataclass
class _Config:
    idle: list = field(default_factory=list)
    made: int = 0  # instances alive, idle or in use
    nbytes: int = 0  # of those instances, as measured when built


class MethodPool:
    """Relocalizers by configuration: ``take(method)`` one (building it when none is idle and fewer than
    ``per_config`` exist, else waiting), ``give`` it back. ``build(method)`` makes one."""

    def __init__(self, build: Callable[[Any], Any], per_config: int = 2, max_bytes: int = 1 << 30):
        self.build, self.per_config, self.max_bytes = build, max(1, per_config), int(max_bytes)
        self._configs: OrderedDict[str, _Config] = OrderedDict()
        self._cond = threading.Condition()
        self.total = 0
        self.built = 0  # instances built over the pool's life

    def take(self, method: Any) -> Any:
        key = config_key(method)
        with self._cond:
            while True:
                c = self._configs.setdefault(key, _Config())
                self._configs.move_to_end(key)
                if c.idle:
                    return c.idle.pop()
                if c.made < self.per_config:
                    c.made += 1
                    break
                self._cond.wait()
        try:
            loc = self.build(method)
        except BaseException:
            with self._cond:
                c.made -= 1
                self._cond.notify_all()
            raise
        after_load()  # a serving process keeps it out of the garbage collector's walks
        n = deep_nbytes(loc)
        with self._cond:
            c.nbytes += n
            self.total += n
            self.built += 1
        self._shrink()
        return loc

    def give(self, method: Any, loc: Any) -> None:
        with self._cond:
            self._configs.setdefault(config_key(method), _Config()).idle.append(loc)
            self._cond.notify_all()
        self._shrink()

    def _shrink(self) -> None:
        """Drop idle instances, least recently used configuration first, while over ``max_bytes``; the most
        recently used configuration keeps one."""
        dropped = []
        with self._cond:
            keys = list(self._configs)
            for i, key in enumerate(keys):
                if self.total <= self.max_bytes:
                    break
                c = self._configs[key]
                keep = 1 if i == len(keys) - 1 else 0
                while len(c.idle) > keep and self.total > self.max_bytes:
                    dropped.append(c.idle.pop(0))
                    share = c.nbytes // max(1, c.made)
                    c.nbytes -= share
                    c.made -= 1
                    self.total -= share
                if c.made == 0:
                    del self._configs[key]
            self._cond.notify_all()
        if dropped:
            del dropped
            after_unload()

    def configs(self) -> int:
        """Configurations with an instance alive."""
        with self._cond:
            return sum(1 for c in self._configs.values() if c.made)

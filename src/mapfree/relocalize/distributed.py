"""``mapfree run --ray``: a split's frames computed by Ray workers on a cluster, journaled by the driver.

The driver (the process that runs ``run_split``) plans the run as a local one does — journal, ``--resume``,
stale scenes, data checks — and then:

1. checks that every alive node reads the dataset root at the same path (a task pinned to each node): a node
   that cannot is one clear error naming the node and the path, before any work;
2. starts one worker (a Ray actor) per slot of the cluster, a slot being ``cpus_per_task`` CPUs and
   ``gpus_per_task`` GPUs of one node; each builds the method once — so its weights are checked on that node —
   and keeps the reference of the scene it works on from one chunk to the next;
3. hands out chunks of frames (a large scene is several chunks, so no scene holds the tail of the run),
   preferring a worker's own scene and otherwise the largest scene no one works on; each chunk streams its
   frames back one by one, and the driver appends them to the journal, advances the progress bar and writes
   the ``--viz`` figures: the journal, ``--resume`` and the failure log mean what they mean locally;
4. when a worker is lost with its node, the frames of its chunk not yet journaled go back to the queue (a
   journaled frame is never computed twice) and new workers start wherever the cluster has room again.

Every frame's result depends on its scene and the method alone (per-call seeded RANSAC, no state shared
between frames), so where it ran does not change the submission.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .cluster import (
    ClusterError,
    alive_nodes,
    check_nodes,
    check_root,
    connect,
    describe_nodes,
    end_actors,
    node_name,
    one_line,
    ray_module,
    task_slots,
    unreadable,
)
from .journal import append_records
from .scenes import (
    FrameResult,
    SceneReference,
    built_localizer,
    check_depth_source,
    open_scene,
    save_figure,
    scene_results,
    set_up_worker,
    sigint_ignored,
)

if TYPE_CHECKING:
    from ..methods import Method

__all__ = ["RayOptions", "ClusterError", "connect", "check_root", "task_slots", "plan_chunks", "run_on_ray"]

_TICK_S = 0.5  # the driver's loop: how long it waits for a result before looking after its workers
_REGROW_S = 2.0  # how often it looks for room for more workers
_START_GRACE_S = 60.0  # how long the first work waits for workers the cluster has no room for yet


@dataclass(frozen=True)
class RayOptions:
    """What each Ray worker asks of its node, and how the frames are cut into tasks.

    ``gpus_per_task=None``: one GPU for a method that runs networks when the cluster has GPUs, else none; a
    fraction (0.25) puts several workers on one GPU. ``chunk_frames=None``: about four chunks per worker, of
    4 to 64 frames. ``lost_wait_s``: how long a run whose workers were all lost waits for room for new ones."""

    cpus_per_task: float = 1.0
    gpus_per_task: float | None = None
    chunk_frames: int | None = None
    lost_wait_s: float = 120.0

    def __post_init__(self) -> None:
        if not self.cpus_per_task > 0:
            raise ValueError(f"--cpus-per-task must be > 0, got {self.cpus_per_task}")
        if self.gpus_per_task is not None and not self.gpus_per_task >= 0:
            raise ValueError(f"--gpus-per-task must be >= 0, got {self.gpus_per_task}")
        if self.gpus_per_task is not None and self.gpus_per_task > 1 and self.gpus_per_task != int(self.gpus_per_task):
            raise ValueError(f"--gpus-per-task above 1 must be a whole number, got {self.gpus_per_task}")
        if self.chunk_frames is not None and self.chunk_frames < 1:
            raise ValueError(f"chunk_frames must be >= 1, got {self.chunk_frames}")


# --------------------------------------------------------------------------- the worker


class FrameWorker:
    """A Ray actor (``ray.remote`` applied when a run starts): the method built once, the reference of the
    scene it works on kept from one chunk to the next. ``threads``: its share of the cores, set by ``setup``."""

    def __init__(self, method: Method, threads: int) -> None:
        self.method, self.threads = method, threads
        self.reference: SceneReference | None = None

    def setup(self, root: str, split: str, scene_dirs: Sequence[str]) -> dict[str, str]:
        """Set up this worker's process (``set_up_worker``), check the data is readable here (a node that joined
        after the start was not checked), build the method (its weights must be on this node) and say where this
        worker runs."""
        import ray

        from .. import __version__

        set_up_worker(self.threads)
        node = node_name()
        problem = check_root(root, split, scene_dirs)
        if problem:
            return {"node": node, "unreadable": problem}
        try:
            check_depth_source(built_localizer(self.method))
        except Exception as e:  # weights or a model missing on this node: one line naming it
            return {"node": node, "error": f"{type(e).__name__}: {e}"}
        return {"node": node, "node_id": ray.get_runtime_context().get_node_id(), "version": __version__}

    def run(self, scene_dir: str, frames: list[str], batch_size: int | None, figures: bool) -> Iterator[FrameResult]:
        """The frames' results, streamed one by one (``scene_results``) against the scene's reference."""
        if self.reference is None or str(self.reference.scene.path) != scene_dir:
            self.reference = open_scene(self.method, scene_dir)
        yield from scene_results(self.reference, self.method, frames, batch_size, figures)

    def run_all(self, scene_dir: str, frames: list[str], batch_size: int | None, figures: bool) -> list[FrameResult]:
        """``run``'s results in one list, for a driver connected through Ray Client (which cannot stream)."""
        return list(self.run(scene_dir, frames, batch_size, figures))


# --------------------------------------------------------------------------- the driver


def plan_chunks(todo: Sequence[tuple[str, list[str]]], workers: int, size: int | None = None) -> int:
    """Frames per chunk: ``size``, or about four chunks per worker, 4 to 64 frames each."""
    if size is not None:
        return size
    total = sum(len(f) for _, f in todo)
    return max(4, min(64, math.ceil(total / max(1, 4 * workers))))


class _Queue:
    """The chunks still to hand out, scene by scene."""

    def __init__(self, todo: Sequence[tuple[str, list[str]]], size: int) -> None:
        self.scenes: dict[str, deque[list[str]]] = {}
        for scene, frames in todo:
            self.scenes[scene] = deque(frames[i : i + size] for i in range(0, len(frames), size))

    def __len__(self) -> int:
        return sum(len(q) for q in self.scenes.values())

    def take(self, prefer: str | None, busy: set[str]) -> tuple[str, list[str]] | None:
        """A chunk of ``prefer`` (the worker's scene: its reference is set up), else of the scene with the most
        frames left that no worker is on, else of the one with the most frames left."""
        left = {s: sum(map(len, q)) for s, q in self.scenes.items() if q}
        if not left:
            return None
        if prefer not in left:
            free = [s for s in left if s not in busy]
            prefer = max(free or left, key=lambda s: left[s])
        chunk = self.scenes[prefer].popleft()
        return prefer, chunk

    def give_back(self, scene: str, frames: list[str]) -> None:
        self.scenes.setdefault(scene, deque()).appendleft(frames)


@dataclass
class _Slot:
    """One worker actor and what it is doing."""

    actor: Any
    setup: Any = None  # the set-up call while it starts
    node: str = ""
    node_id: str = ""
    scene: str | None = None
    frames: list[str] = field(default_factory=list)  # handed over, not yet received
    stream: Any = None  # the chunk's result stream while busy


@dataclass
class ClusterRun:
    """What the cluster did: the address, how many nodes and workers took part, chunks handed out (tasks),
    frames handed out again after their worker was lost."""

    address: str
    nodes: int = 0
    workers: int = 0
    tasks: int = 0
    requeued: int = 0

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def run_on_ray(
    method: Method,
    todo: Sequence[tuple[str, list[str]]],
    journal: Path,
    bar: Any,
    address: str,
    options: RayOptions,
    root: str,
    split: str,
    batch_size: int | None = None,
    viz_dir: str | None = None,
) -> ClusterRun:
    """Compute ``todo`` (``[(absolute scene folder, frame names)]``) on the Ray cluster at ``address``, appending
    each frame's record to ``journal`` as it arrives (see the module docstring). ``method``: a ``Method``."""
    ray = ray_module()
    started = connect(address)
    try:
        return _Driver(ray, method, todo, journal, bar, address, options, root, split, batch_size, viz_dir).run()
    finally:
        if started:
            ray.shutdown()


class _Driver:
    def __init__(
        self,
        ray: Any,
        method: Method,
        todo: Sequence[tuple[str, list[str]]],
        journal: Path,
        bar: Any,
        address: str,
        options: RayOptions,
        root: str,
        split: str,
        batch_size: int | None,
        viz_dir: str | None,
    ) -> None:
        self.ray, self.method, self.todo, self.journal, self.bar = ray, method, todo, journal, bar
        self.root, self.split, self.scene_dirs = root, split, [scene for scene, _ in todo]
        self.options, self.batch_size, self.viz_dir = options, batch_size, viz_dir
        self.slots: list[_Slot] = []
        self.info = ClusterRun(address)
        self.seen_nodes: set[str] = set()
        self.journaled: set[tuple[str, str]] = set()
        self.start_failures = 0
        # Ray Client (ray://) cannot stream a task's results: its chunks come back whole.
        self.streaming = not ray.util.client.ray.is_connected()

    # ---- set-up

    def _resources(self, nodes: Sequence[dict]) -> tuple[float, float]:
        gpus = self.options.gpus_per_task
        if gpus is None:
            has_gpu = any(n["Resources"].get("GPU", 0) > 0 for n in nodes)
            gpus = 1.0 if has_gpu and self.method.networks else 0.0
        return self.options.cpus_per_task, gpus

    def _start_worker(self) -> None:
        cpus, gpus = self.resources
        actor = self.worker_cls.options(num_cpus=cpus, num_gpus=gpus, max_restarts=0, max_task_retries=0).remote(
            self.method, max(1, int(cpus))
        )
        self.slots.append(_Slot(actor, setup=actor.setup.remote(self.root, self.split, self.scene_dirs)))

    def _grow(self, nodes: Sequence[dict] | None = None) -> None:
        """Start workers while the cluster has room and the queue has chunks for them."""
        nodes = alive_nodes(self.ray) if nodes is None else nodes
        room = task_slots(nodes, *self.resources) - len(self.slots)
        want = len(self.queue) - sum(s.setup is not None or s.stream is None for s in self.slots)
        for _ in range(max(0, min(room, want))):
            self._start_worker()

    def run(self) -> ClusterRun:
        ray = self.ray
        self.nodes = nodes = alive_nodes(ray)
        self.resources = self._resources(nodes)
        slots = task_slots(nodes, *self.resources)
        if slots == 0:
            raise ValueError(
                f"no node of the Ray cluster has room for a worker of {self.resources[0]:g} CPU(s) and "
                f"{self.resources[1]:g} GPU(s) (--cpus-per-task, --gpus-per-task); its nodes: "
                f"{describe_nodes(nodes)}"
            )
        self.queue = _Queue(self.todo, plan_chunks(self.todo, slots, self.options.chunk_frames))
        self.worker_cls = ray.remote(FrameWorker)
        try:
            self._grow(nodes)  # the workers start (and load the method) while every node checks the data
            check_nodes(ray, nodes, self.root, self.split, self.scene_dirs)
            self._wait_for_setups()
            self._loop()
        finally:
            with sigint_ignored():  # Ctrl-C or an error included: nothing keeps running for this run
                end_actors(ray, [s.actor for s in self.slots])
        return self.info

    def _setup_done(self, slot: _Slot) -> None:
        """A worker finished its set-up: fail the run on a node that cannot run the method, else put it to work."""
        ray = self.ray
        ref, slot.setup = slot.setup, None
        try:
            answer = ray.get(ref)
        except ray.exceptions.RayActorError as e:  # its node went away meanwhile, or the cluster refused it
            self._drop(slot)
            self.start_failures += 1
            if not self.seen_nodes and self.start_failures >= 2 * max(1, task_slots(self.nodes, *self.resources)):
                why = one_line(e)
                raise ClusterError(
                    f"the Ray cluster ended all {self.start_failures} workers started so far before "
                    f"any ran ({why}); see its logs (the driver's included)"
                ) from None
            return
        except ray.exceptions.RayError as e:
            last = str(e).strip().splitlines()[-1]  # a task error's text ends with the exception
            raise ClusterError(f"a worker could not start: {last} (is mapfree installed on every node?)") from None
        if "unreadable" in answer:
            raise unreadable(answer["node"], self.root, answer["unreadable"])
        if "error" in answer:
            raise FileNotFoundError(f"node {answer['node']} cannot run method {self.method.name!r}: {answer['error']}")
        from .. import __version__

        if answer["version"] != __version__:
            raise ClusterError(
                f"node {answer['node']} runs mapfree {answer['version']}, this machine {__version__}: "
                f"install the same version on every node"
            )
        slot.node, slot.node_id = answer["node"], answer["node_id"]
        self.seen_nodes.add(slot.node_id)

    def _wait_for_setups(self) -> None:
        """The first workers set up before any work: a node without the weights stops the run here. Workers the
        cluster has no room for yet (busy with other jobs) join later, once ``_START_GRACE_S`` has passed."""
        t0 = time.monotonic()
        while any(s.setup is not None for s in self.slots):
            if self._live() and time.monotonic() - t0 > _START_GRACE_S:
                return
            pending = {s.setup: s for s in self.slots if s.setup is not None}
            ready, _ = self.ray.wait(list(pending), num_returns=1, timeout=_TICK_S)
            for ref in ready:
                self._setup_done(pending[ref])
            self._show()

    # ---- the loop

    def _live(self) -> list[_Slot]:
        return [s for s in self.slots if s.setup is None]

    def _show(self) -> None:
        live = self._live()
        nodes = len({s.node_id for s in live})
        starting = len(self.slots) - len(live)
        self.info.workers = max(self.info.workers, len(live))
        self.info.nodes = len(self.seen_nodes)
        text = f"{len(live)} workers on {nodes} node{'s' * (nodes != 1)}"
        self.bar.set_postfix_str(text + (f", {starting} starting" if starting else ""), refresh=False)

    def _dispatch(self) -> None:
        busy = {s.scene for s in self.slots if s.stream is not None and s.scene is not None}
        for slot in self._live():
            if slot.stream is not None:
                continue
            job = self.queue.take(slot.scene, busy)
            if job is None:
                return
            slot.scene, slot.frames = job
            busy.add(slot.scene)
            self.info.tasks += 1
            args = (slot.scene, list(slot.frames), self.batch_size, self.viz_dir is not None)
            if self.streaming:
                slot.stream = slot.actor.run.options(num_returns="streaming").remote(*args)
            else:
                slot.stream = slot.actor.run_all.remote(*args)

    def _drop(self, slot: _Slot) -> None:
        """A lost worker: its unfinished frames go back to the queue."""
        if slot.stream is not None and slot.frames and slot.scene is not None:
            self.queue.give_back(slot.scene, slot.frames)
            self.info.requeued += len(slot.frames)
            self.bar.write(
                f"mapfree run: lost the worker on node {slot.node or '?'}: its {len(slot.frames)} "
                f"unfinished frame(s) go to another worker"
            )
        self.slots.remove(slot)
        self.ray.kill(slot.actor, no_restart=True)

    def _receive(self, slot: _Slot) -> None:
        """The next result of a busy worker's stream, or the end of its chunk (all of it without streaming)."""
        ray = self.ray
        try:
            results: list[FrameResult] = [ray.get(next(slot.stream))] if self.streaming else ray.get(slot.stream)
        except StopIteration:
            results = []
        except (ray.exceptions.RayActorError, ray.exceptions.ObjectLostError):
            self._drop(slot)
            return
        for result in results:
            self._journal(slot, result)
        if not results or not self.streaming:  # the chunk is over
            if slot.frames and slot.scene is not None:  # short of its frames: hand them out again
                self.queue.give_back(slot.scene, slot.frames)
                slot.frames = []
            slot.stream = None

    def _journal(self, slot: _Slot, result: FrameResult) -> None:
        """Append a frame's record to the journal (never twice), write its figure, advance the bar."""
        rec = result.record
        if rec.frame in slot.frames:
            slot.frames.remove(rec.frame)
        if rec.key in self.journaled:
            return
        append_records(self.journal, [rec])
        self.journaled.add(rec.key)
        save_figure(self.viz_dir, result)
        self.bar.update(1)

    def _loop(self) -> None:
        ray = self.ray
        last_grow = lost_since = time.monotonic()
        while len(self.queue) or any(s.stream is not None for s in self.slots):
            self._dispatch()
            waiting = {s.stream: s for s in self.slots if s.stream is not None}
            waiting.update({s.setup: s for s in self.slots if s.setup is not None})
            ready = ray.wait(list(waiting), num_returns=1, timeout=_TICK_S)[0] if waiting else []
            if not waiting:  # every worker lost: wait for room for new ones
                time.sleep(_TICK_S)
            for ref in ready:
                slot = waiting[ref]
                if slot.setup is not None:
                    self._setup_done(slot)
                elif slot in self.slots:
                    self._receive(slot)
            now = time.monotonic()
            if now - last_grow > _REGROW_S:
                last_grow = now
                self._grow()
            if self._live():
                lost_since = now
            elif now - lost_since > self.options.lost_wait_s:
                raise ClusterError(
                    f"every worker was lost and the cluster has had no room for a new one for "
                    f"{self.options.lost_wait_s:.0f} s (nodes: {describe_nodes(alive_nodes(ray))}); the "
                    f"finished frames are journaled: run again with --resume"
                )
            self._show()

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

import logging
import math
import os
import socket
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .scenes import (
    FrameResult,
    SceneReference,
    append_records,
    built_localizer,
    check_depth_source,
    open_scene,
    save_figure,
    scene_results,
    set_threads,
    sigint_ignored,
)

if TYPE_CHECKING:
    from ..methods import Method

__all__ = ["RayOptions", "ClusterError", "connect", "check_root", "task_slots", "plan_chunks", "run_on_ray"]

LOCAL = "local"  # the address that starts a Ray instance on this machine
_TICK_S = 0.5  # the driver's loop: how long it waits for a result before looking after its workers
_REGROW_S = 2.0  # how often it looks for room for more workers
_START_GRACE_S = 60.0  # how long the first work waits for workers the cluster has no room for yet


class ClusterError(RuntimeError):
    """The Ray cluster cannot run the work (unreachable, no room for a worker, every worker lost); the message
    says what to do, and the frames journaled so far are kept for ``--resume``."""


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


# --------------------------------------------------------------------------- the cluster


def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise ClusterError("--ray needs Ray on this machine and every node: pip install 'mapfree[cluster]'") from None
    return ray


def connect(address: str) -> bool:
    """Join the Ray cluster at ``address`` (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``), or start a Ray
    instance on this machine for ``local``. True when this call connected (so the caller disconnects), False
    when this process was connected already."""
    if address == LOCAL:
        # A local instance talks only to itself: keep it on the loopback address (Ray reads this at import).
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    ray = _ray()
    if ray.is_initialized():
        return False
    if address not in (LOCAL, "auto"):
        _check_reachable(address)
    quiet = {"log_to_driver": False, "configure_logging": False, "logging_level": logging.WARNING}
    if address == LOCAL:
        try:
            ray.init(address="local", include_dashboard=False, object_store_memory=256 * 1024 * 1024, **quiet)
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise ClusterError(f"cannot start a local Ray instance: {_one_line(e)}") from None
        return True
    # Ray's core prints each refused attempt on stderr (for about 20 s) before giving up with "Failed to
    # connect": what it printed tells a cluster that refused this driver's token from one that is not there.
    with _stderr_kept() as said:
        try:
            ray.init(address=address, **quiet)
        except ray.exceptions.AuthenticationError:  # RAY_AUTH_MODE=token here, but no token
            raise ClusterError(token_refused(address, "this machine has no token")) from None
        except (ConnectionError, RuntimeError, ValueError) as e:
            if any(mark in said() for mark in _AUTH_REFUSED):
                raise ClusterError(token_refused(address, _token_state())) from None
            raise ClusterError(f"cannot reach the Ray cluster at {address}: {_one_line(e)}") from None
    return True


#: What Ray's core prints when the cluster refuses a driver's token (or the lack of one).
_AUTH_REFUSED = ("InvalidAuthToken", "Unauthenticated")


def token_refused(address: str, why: str) -> str:
    """The one line for a cluster that refused this driver for want of its token (``why``: what is here)."""
    return (
        f"the Ray cluster at {address} refused this driver: it uses token authentication and {why}: run with "
        f"RAY_AUTH_MODE=token and the cluster's token (`ray get-auth-token` on the head prints it) in "
        f"RAY_AUTH_TOKEN or ~/.ray/auth_token"
    )


def _token_state() -> str:
    """What this driver sent, in words, for ``token_refused``."""
    if os.environ.get("RAY_AUTH_MODE", "").lower() != "token":
        return "RAY_AUTH_MODE is not 'token' here, so no token was sent"
    return "the token here is not the cluster's"


@contextmanager
def _stderr_kept() -> Iterator[Callable[[], str]]:
    """Route file descriptor 2 (where Ray's C++ core writes) to a temporary file within the block; yields what
    it holds so far. After a block that raised, the text is dropped (the caller words the error); otherwise
    it is written to stderr as it would have been."""
    import sys
    import tempfile

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)

        def said() -> str:
            tmp.seek(0)
            return tmp.read().decode(errors="replace")

        try:
            yield said
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        sys.stderr.write(said())


def _one_line(e: BaseException, limit: int = 300) -> str:
    """A Ray error's text on one line (its messages span several), cut at ``limit`` characters."""
    text = " ".join(str(e).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """Refuse at once a ``[ray://]HOST:PORT`` nothing answers at (Ray itself would keep retrying for minutes)."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise ClusterError(f"--ray {address}: expected 'auto', HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as e:
        raise ClusterError(
            f"cannot reach the Ray cluster at {address}: {e.strerror or e} (is `ray start --head` "
            f"running there, and the port open?)"
        ) from None


def _alive_nodes(ray: Any) -> list[dict]:
    return [n for n in ray.nodes() if n.get("Alive")]


def task_slots(nodes: Sequence[dict], cpus: float, gpus: float) -> int:
    """How many workers of ``cpus`` CPUs and ``gpus`` GPUs the ``nodes`` (``ray.nodes()`` entries) hold."""
    total = 0
    for n in nodes:
        res = n.get("Resources", {})
        fit = [math.floor(res.get("CPU", 0.0) / cpus + 1e-9)]
        if gpus > 0:
            fit.append(math.floor(res.get("GPU", 0.0) / gpus + 1e-9))
        total += max(0, min(fit))
    return total


def _describe(nodes: Sequence[dict]) -> str:
    return (
        "; ".join(
            f"{n.get('NodeManagerAddress', '?')}: {n['Resources'].get('CPU', 0):g} CPU, "
            f"{n['Resources'].get('GPU', 0):g} GPU"
            for n in nodes
        )
        or "none alive"
    )


def _node_name() -> str:
    """This worker's node, for messages: its address, host name and Ray node id."""
    import ray

    node_id = ray.get_runtime_context().get_node_id()
    return f"{ray.util.get_node_ip_address()} ({socket.gethostname()}, node {node_id[:8]})"


# --------------------------------------------------------------------------- checks on every node


def check_root(root: str, split: str, scene_dirs: Sequence[str]) -> str | None:
    """Why this machine cannot read a run's data under ``root`` (the split folder, each scene's folder and its
    ``intrinsics.txt``), or None when it can."""
    try:
        os.listdir(os.path.join(root, split))
        for d in scene_dirs:
            os.listdir(d)
            with open(os.path.join(d, "intrinsics.txt"), "rb") as f:
                f.read(1)
    except OSError as e:
        return f"{e.strerror or type(e).__name__}: {e.filename}"
    return None


def _node_check(root: str, split: str, scene_dirs: Sequence[str]) -> tuple[str, str | None]:
    return _node_name(), check_root(root, split, scene_dirs)


def _check_nodes(ray: Any, nodes: Sequence[dict], root: str, split: str, scene_dirs: Sequence[str]) -> None:
    """Run ``check_root`` on every node (a task pinned there): the first node that cannot read the data fails
    the run with one line naming it and the path."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    check = ray.remote(num_cpus=0, max_retries=0)(_node_check)
    refs = [
        check.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote(
            root, split, list(scene_dirs)
        )
        for n in nodes
    ]
    try:
        answers = ray.get(refs, timeout=300)
    except ray.exceptions.GetTimeoutError:
        raise ClusterError("a node of the Ray cluster did not answer the data check within 5 minutes") from None
    for node, problem in answers:
        if problem:
            raise _unreadable(node, root, problem)


def end_actors(ray: Any, actors: Sequence[Any], wait_s: float = 10.0) -> None:
    """Kill the run's workers and wait (up to ``wait_s``) until the cluster reports each one gone, so that no
    worker process outlives the run (``ray.kill`` only asks; a driver that left at once left busy workers
    behind)."""
    for actor in actors:
        ray.kill(actor, no_restart=True)
    # a call to a killed actor fails (ActorDiedError) once the cluster has its process dead
    probes = [actor.__ray_ready__.remote() for actor in actors]
    if probes:
        ray.wait(probes, num_returns=len(probes), timeout=wait_s)


def _unreadable(node: str, root: str, problem: str) -> FileNotFoundError:
    return FileNotFoundError(
        f"node {node} cannot read the dataset root {root} ({problem}): every node needs the "
        f"dataset at the same path (shared storage)"
    )


# --------------------------------------------------------------------------- the worker


class FrameWorker:
    """A Ray actor (``ray.remote`` applied when a run starts): the method built once, the reference of the
    scene it works on kept from one chunk to the next."""

    def __init__(self, method: Method, threads: int) -> None:
        set_threads(threads)
        self.method = method
        self.reference: SceneReference | None = None

    def setup(self, root: str, split: str, scene_dirs: Sequence[str]) -> dict[str, str]:
        """Check the data is readable here (a node that joined after the start was not checked), build the method
        (its weights must be on this node) and say where this worker runs."""
        import ray

        from .. import __version__

        node = _node_name()
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
    ray = _ray()
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
        nodes = _alive_nodes(self.ray) if nodes is None else nodes
        room = task_slots(nodes, *self.resources) - len(self.slots)
        want = len(self.queue) - sum(s.setup is not None or s.stream is None for s in self.slots)
        for _ in range(max(0, min(room, want))):
            self._start_worker()

    def run(self) -> ClusterRun:
        ray = self.ray
        self.nodes = nodes = _alive_nodes(ray)
        self.resources = self._resources(nodes)
        slots = task_slots(nodes, *self.resources)
        if slots == 0:
            raise ValueError(
                f"no node of the Ray cluster has room for a worker of {self.resources[0]:g} CPU(s) and "
                f"{self.resources[1]:g} GPU(s) (--cpus-per-task, --gpus-per-task); its nodes: "
                f"{_describe(nodes)}"
            )
        self.queue = _Queue(self.todo, plan_chunks(self.todo, slots, self.options.chunk_frames))
        self.worker_cls = ray.remote(FrameWorker)
        try:
            self._grow(nodes)  # the workers start (and load the method) while every node checks the data
            _check_nodes(ray, nodes, self.root, self.split, self.scene_dirs)
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
                why = _one_line(e)
                raise ClusterError(
                    f"the Ray cluster ended all {self.start_failures} workers started so far before "
                    f"any ran ({why}); see its logs (the driver's included)"
                ) from None
            return
        except ray.exceptions.RayError as e:
            last = str(e).strip().splitlines()[-1]  # a task error's text ends with the exception
            raise ClusterError(f"a worker could not start: {last} (is mapfree installed on every node?)") from None
        if "unreadable" in answer:
            raise _unreadable(answer["node"], self.root, answer["unreadable"])
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
        key = (rec["scene"], rec["frame"])
        if rec["frame"] in slot.frames:
            slot.frames.remove(rec["frame"])
        if key in self.journaled:
            return
        append_records(self.journal, [rec])
        self.journaled.add(key)
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
                    f"{self.options.lost_wait_s:.0f} s (nodes: {_describe(_alive_nodes(ray))}); the "
                    f"finished frames are journaled: run again with --resume"
                )
            self._show()

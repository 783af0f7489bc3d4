"""The Ray cluster as ``mapfree run --ray`` uses it: joining it (or starting a local instance), the clear errors
of one that cannot be reached or refuses this driver's token, the room its nodes have for workers, the data check
on every node and the end of a run's workers. ``distributed.py`` drives a run over it."""

from __future__ import annotations

import logging
import math
import os
import socket
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

__all__ = [
    "LOCAL",
    "ClusterError",
    "ray_module",
    "connect",
    "token_refused",
    "one_line",
    "alive_nodes",
    "task_slots",
    "describe_nodes",
    "node_name",
    "check_root",
    "check_nodes",
    "end_actors",
    "unreadable",
]

LOCAL = "local"  # the address that starts a Ray instance on this machine


class ClusterError(RuntimeError):
    """The Ray cluster cannot run the work (unreachable, no room for a worker, every worker lost); the message
    says what to do, and the frames journaled so far are kept for ``--resume``."""


# --------------------------------------------------------------------------- the cluster


def ray_module() -> Any:
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
    ray = ray_module()
    if ray.is_initialized():
        return False
    if address not in (LOCAL, "auto"):
        _check_reachable(address)
    quiet = {"log_to_driver": False, "configure_logging": False, "logging_level": logging.WARNING}
    if address == LOCAL:
        try:
            ray.init(address="local", include_dashboard=False, object_store_memory=256 * 1024 * 1024, **quiet)
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise ClusterError(f"cannot start a local Ray instance: {one_line(e)}") from None
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
            raise ClusterError(f"cannot reach the Ray cluster at {address}: {one_line(e)}") from None
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


def one_line(e: BaseException, limit: int = 300) -> str:
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


def alive_nodes(ray: Any) -> list[dict]:
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


def describe_nodes(nodes: Sequence[dict]) -> str:
    return (
        "; ".join(
            f"{n.get('NodeManagerAddress', '?')}: {n['Resources'].get('CPU', 0):g} CPU, "
            f"{n['Resources'].get('GPU', 0):g} GPU"
            for n in nodes
        )
        or "none alive"
    )


def node_name() -> str:
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
    return node_name(), check_root(root, split, scene_dirs)


def check_nodes(ray: Any, nodes: Sequence[dict], root: str, split: str, scene_dirs: Sequence[str]) -> None:
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
            raise unreadable(node, root, problem)


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


def unreadable(node: str, root: str, problem: str) -> FileNotFoundError:
    return FileNotFoundError(
        f"node {node} cannot read the dataset root {root} ({problem}): every node needs the "
        f"dataset at the same path (shared storage)"
    )

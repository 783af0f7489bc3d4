"""A Ray cluster on this machine for tests, kept in a process of its own.

``python tests/raycluster.py cluster [N]`` starts a head and N (2) worker nodes of one CPU each
(``ray.cluster_utils.Cluster``; with ``$RAY_AUTH_TOKEN`` set, one that requires that token), prints one JSON line ``{"address", "client", "workers"}`` and then obeys one
command per stdin line, answering ``ok``: ``kill I`` (worker node I dies at once, as a lost machine),
``add_gpu`` (a node of 2 CPUs declaring one GPU). End of input shuts it down.

``python tests/raycluster.py node ADDRESS`` joins one more worker node to the cluster at ADDRESS, prints its id
and stops its processes on SIGTERM (the test runs it where the dataset is hidden from it).

Ray keeps process-wide state (its authentication mode, read once) that an earlier ``ray.init`` in the test
process would set differently; here, and in the drivers the tests start as ``mapfree run`` processes, every
Ray process starts clean.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import sys
import time

MB = 1024 * 1024
# A lost node is noticed within about a second (Ray's default waits tens of seconds for a real network).
FAST_HEALTH = {"health_check_period_ms": 300, "health_check_failure_threshold": 3, "health_check_timeout_ms": 300}
# What every process of these clusters shares: the loopback address, no token to hand around, no downloads.
ENV = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_AUTH_MODE": "disabled", "MAPFREE_OFFLINE": "1"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cluster(workers: int = 2) -> None:
    from ray.cluster_utils import Cluster

    port = _free_port()
    c = Cluster(
        initialize_head=True,
        head_node_args={
            "num_cpus": 1,
            "include_dashboard": False,
            "object_store_memory": 80 * MB,
            "_system_config": FAST_HEALTH,
            "ray_client_server_port": port,
        },
    )
    nodes = [c.add_node(num_cpus=1, object_store_memory=80 * MB) for _ in range(workers)]
    c.wait_for_nodes()
    print(
        json.dumps({"address": c.address, "client": f"ray://127.0.0.1:{port}", "workers": [n.node_id for n in nodes]}),
        flush=True,
    )
    try:
        for line in sys.stdin:
            cmd = line.split()
            if cmd[:1] == ["kill"]:
                c.remove_node(nodes[int(cmd[1])], allow_graceful=False)
            elif cmd == ["add_gpu"]:
                c.add_node(num_cpus=2, num_gpus=1, object_store_memory=80 * MB)
                c.wait_for_nodes()
            print("ok", flush=True)
    finally:
        c.shutdown()


def node(address: str) -> None:
    from ray._private.node import Node
    from ray._private.parameter import RayParams

    params = RayParams(
        num_cpus=1,
        num_gpus=0,
        object_store_memory=80 * MB,
        min_worker_port=0,
        max_worker_port=0,
        gcs_address=address,
        include_log_monitor=False,
        node_manager_port=0,
    )
    params.dashboard_agent_listen_port = None
    n = Node(params, head=False, shutdown_at_exit=True, spawn_reaper=True)

    def stop(*_: object) -> None:
        n.kill_all_processes(check_alive=False, allow_graceful=True)
        sys.exit(0)

    signal.signal(signal.SIGTERM, stop)
    print(n.node_id, flush=True)
    while True:
        time.sleep(1)


if __name__ == "__main__":
    os.environ.update(ENV)
    if os.environ.get("RAY_AUTH_TOKEN"):  # a cluster that refuses drivers without this token
        os.environ["RAY_AUTH_MODE"] = "token"
    if sys.argv[1] == "cluster":
        cluster(int(sys.argv[2]) if len(sys.argv) > 2 else 2)
    else:
        node(sys.argv[2])

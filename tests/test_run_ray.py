"""``mapfree run --ray`` on a real three-node Ray cluster on this machine: the same submission as a local run,
a lost node or a killed driver costs no frame and journals none twice, a node without the data is one clear line.

One cluster (``ray.cluster_utils.Cluster``: a head and two worker nodes of one CPU each) serves the module; the
split is synthetic (3 scenes of 30 small queries) and the method SIFT + PnP, so a whole run takes seconds.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

from mapfree.cli import main  # noqa: E402
from mapfree.data.synth import SynthOptions, generate  # noqa: E402
from mapfree.relocalize import read_journal, run_split  # noqa: E402
from mapfree.relocalize.distributed import ClusterError, RayOptions, task_slots  # noqa: E402

pytestmark = pytest.mark.slow

METHOD = "sift_pnp_sensor"
SCENES, QUERIES = 3, 30
TOTAL = SCENES * QUERIES  # --all-frames
MB = 1024 * 1024
# A lost node is noticed within about a second (Ray's default waits tens of seconds for a real network).
FAST_HEALTH = {"health_check_period_ms": 300, "health_check_failure_threshold": 3, "health_check_timeout_ms": 300}


@pytest.fixture(scope="module")
def split(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ray-split")
    generate(root, "val", SCENES, QUERIES, options=SynthOptions(width=320, height=240, write_mono=False),
             progress=False)
    return root


@pytest.fixture(scope="module")
def local(split, tmp_path_factory) -> Path:
    """The local run every cluster run must equal, byte for byte."""
    out = tmp_path_factory.mktemp("local") / "sub.zip"
    res = run_split(split, "val", METHOD, out, all_frames=True, progress=False)
    assert res.computed == TOTAL and 0 < res.estimated < TOTAL  # some queries see nothing: failures, too
    return out


@pytest.fixture(scope="module")
def cluster():
    from ray.cluster_utils import Cluster

    old = {k: os.environ.get(k) for k in ("RAY_AUTH_MODE", "MAPFREE_OFFLINE")}
    os.environ["RAY_AUTH_MODE"] = "disabled"  # a throw-away loopback cluster: no token to hand around
    os.environ["MAPFREE_OFFLINE"] = "1"  # the nodes' environment: weights not on disk fail at once
    with socket.socket() as s:  # a free port for the head's Ray Client server (ray://)
        s.bind(("127.0.0.1", 0))
        client_port = s.getsockname()[1]
    c = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 1, "include_dashboard": False, "object_store_memory": 80 * MB, "_system_config": FAST_HEALTH,
        "ray_client_server_port": client_port})
    c.client_address = f"ray://127.0.0.1:{client_port}"
    workers = [c.add_node(num_cpus=1, object_store_memory=80 * MB) for _ in range(2)]
    c.wait_for_nodes()
    try:
        yield c, workers
    finally:
        if ray.is_initialized():
            ray.shutdown()
        c.shutdown()
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _same_outputs(a: Path, b: Path) -> None:
    assert a.read_bytes() == b.read_bytes()
    fa, fb = (p.with_name(p.stem + ".failures.jsonl") for p in (a, b))
    assert fa.read_text() == fb.read_text()


def _keys(journal: Path) -> list[tuple[str, str]]:
    return [(r["scene"], r["frame"]) for r in read_journal(journal)[1]]


def test_three_nodes_write_the_local_submission_byte_for_byte(split, local, cluster, tmp_path):
    c, _ = cluster
    out = tmp_path / "sub.zip"
    res = run_split(split, "val", METHOD, out, all_frames=True, progress=False, ray_address=c.address)
    assert res.computed == TOTAL and res.cluster["nodes"] == 3 and res.cluster["workers"] == 3
    assert res.cluster["requeued"] == 0
    _same_outputs(local, out)
    keys = _keys(res.journal)
    assert len(keys) == len(set(keys)) == TOTAL
    with zipfile.ZipFile(out) as z:
        assert sorted(z.namelist()) == [f"pose_s{i:05d}.txt" for i in range(SCENES)]
    # A GPU per worker on a cluster without GPUs: refused at once, naming what the nodes hold.
    with pytest.raises(ValueError, match=r"no node of the Ray cluster has room for a worker of 1 CPU\(s\) and 1 GPU"):
        run_split(split, "val", METHOD, tmp_path / "gpu.zip", progress=False, ray_address=c.address,
                  ray_options=RayOptions(gpus_per_task=1))
    # A finished run resumed: nothing to compute, the cluster is not even reached.
    again = run_split(split, "val", METHOD, out, all_frames=True, progress=False, resume=True, ray_address="ray://x:1")
    assert again.computed == 0 and again.skipped == TOTAL and again.cluster == {}


def test_multi_frame_track_and_figures_equal_the_local_ones(split, cluster, tmp_path, capsys):
    """The CLI with --track multi --viz --ray ADDRESS: the fused submission and every figure equal a local run's."""
    c, _ = cluster
    for where, extra in (("local", []), ("ray", ["--ray", c.address])):
        rc = main(["run", str(split), "--method", METHOD, "-o", str(tmp_path / where / "m.zip"), "--track", "multi",
                   "--scenes", "s00001", "--viz", str(tmp_path / where / "viz"), "--no-progress", *extra])
        assert rc == 0
    out = capsys.readouterr().out
    assert f"computed on the Ray cluster {c.address}: " in out
    _same_outputs(tmp_path / "local/m.zip", tmp_path / "ray/m.zip")
    assert (tmp_path / "local/m.frames.zip").read_bytes() == (tmp_path / "ray/m.frames.zip").read_bytes()
    figures = sorted(p.relative_to(tmp_path / "local/viz") for p in (tmp_path / "local/viz").rglob("*.png"))
    assert len(figures) == 3 * 9  # 30 queries: 3 bursts of 9 frames
    assert figures == sorted(p.relative_to(tmp_path / "ray/viz") for p in (tmp_path / "ray/viz").rglob("*.png"))
    for f in figures:
        assert (tmp_path / "local/viz" / f).read_bytes() == (tmp_path / "ray/viz" / f).read_bytes(), f


def test_through_ray_client_the_same_poses(split, local, cluster, tmp_path):
    """A driver outside the cluster (--ray ray://HOST:PORT, Ray Client: chunks come back whole, not streamed)."""
    c, _ = cluster
    out = tmp_path / "client.zip"
    res = run_split(split, "val", METHOD, out, all_frames=True, progress=False, ray_address=c.client_address,
                    scenes=["s00002"])
    assert res.computed == QUERIES and res.cluster["workers"] == 3 and not ray.is_initialized()
    with zipfile.ZipFile(local) as a, zipfile.ZipFile(out) as b:
        assert b.namelist() == ["pose_s00002.txt"] and b.read("pose_s00002.txt") == a.read("pose_s00002.txt")


def test_resume_after_the_driver_is_killed_computes_only_the_missing_frames(split, local, cluster, tmp_path):
    c, _ = cluster
    out = tmp_path / "sub.zip"
    journal = out.with_name("sub.journal.jsonl")
    cmd = [sys.executable, "-m", "mapfree", "run", str(split), "--method", METHOD, "-o", str(out), "--all-frames",
           "--no-progress", "--ray", c.address]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None and len(_keys(journal)) < 10:
            time.sleep(0.05)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # the driver only: the cluster's processes are not its children
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, f"the run ended before it could be killed: {proc.stderr.read()}"
    before = read_journal(journal)[1]
    assert 10 <= len(before) < TOTAL and not out.exists()

    res = run_split(split, "val", METHOD, out, all_frames=True, resume=True, progress=False, ray_address=c.address)
    after = read_journal(journal)[1]
    keys = [(r["scene"], r["frame"]) for r in after]
    assert len(keys) == len(set(keys)) == TOTAL  # nothing lost, nothing journaled twice
    assert res.skipped == len(before) and res.computed == TOTAL - len(before)
    assert after[: len(before)] == before
    _same_outputs(local, out)


def test_weights_missing_on_the_nodes_stop_the_run_before_any_work(split, cluster, tmp_path, capsys):
    """SuperGlue's weights are on no node (nor downloadable here): each worker builds the method on its node, and
    the first to fail ends the run in one line naming its node and where the weights go; nothing is journaled."""
    c, _ = cluster
    out = tmp_path / "sg.zip"
    assert main(["run", str(split), "--method", "superglue_pnp_sensor", "-o", str(out), "--no-progress",
                 "--scenes", "s00000", "--ray", c.address]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot run method 'superglue_pnp_sensor'" in err[0], err
    assert f"node 127.0.0.1 ({socket.gethostname()}, node " in err[0] and "$MAPFREE_WEIGHTS_DIR" in err[0], err
    assert not read_journal(out.with_name("sg.journal.jsonl"))[1] and not out.exists()


# A worker node of the cluster at sys.argv[1], started as ``Cluster.add_node`` does (``ray start`` would leave the
# loopback address); it prints its id, and SIGTERM stops its processes.
_NODE = """
import signal, sys, time
from ray._private.node import Node
from ray._private.parameter import RayParams

params = RayParams(num_cpus=1, num_gpus=0, object_store_memory=int(sys.argv[2]), min_worker_port=0,
                   max_worker_port=0, gcs_address=sys.argv[1], include_log_monitor=False, node_manager_port=0)
params.dashboard_agent_listen_port = None
node = Node(params, head=False, shutdown_at_exit=True, spawn_reaper=True)


def stop(*_):
    node.kill_all_processes(check_alive=False, allow_graceful=True)
    sys.exit(0)


signal.signal(signal.SIGTERM, stop)
print(node.node_id, flush=True)
while True:
    time.sleep(1)
"""


def test_a_node_that_cannot_read_the_dataset_is_one_clear_line(split, cluster, tmp_path, capsys):
    """A node whose mount namespace hides the dataset root (as a machine without the shared storage mounted):
    the run fails before any work, naming that node and the root; no frame is journaled."""
    c, _ = cluster
    if shutil.which("unshare") is None or subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode:
        pytest.skip("needs mount namespaces (unshare -m) to hide the dataset from one node")
    empty = tmp_path / "empty"
    empty.mkdir()
    start = f'mount --bind "{empty}" "{split}" && exec "{sys.executable}" -c "$0" "$@"'
    node = subprocess.Popen(["unshare", "-m", "--propagation", "private", "sh", "-c", start, _NODE, c.address,
                             str(80 * MB)], start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True)
    out = tmp_path / "sub.zip"
    try:
        blind = node.stdout.readline().strip()
        assert blind, f"the node without the dataset did not start (exit {node.poll()})"
        with pytest.raises(FileNotFoundError) as err:
            run_split(split, "val", METHOD, out, all_frames=True, progress=False, ray_address=c.address)
        msg = str(err.value)
        assert f"node {blind[:8]})" in msg and f"cannot read the dataset root {split}" in msg, msg
        assert "\n" not in msg and not read_journal(out.with_name("sub.journal.jsonl"))[1]
        assert main(["run", str(split), "--method", METHOD, "-o", str(out), "--overwrite", "--no-progress",
                     "--ray", c.address]) == 1
        err_lines = capsys.readouterr().err.strip().splitlines()
        assert len(err_lines) == 1 and "cannot read the dataset root" in err_lines[0], err_lines
    finally:
        _stop(node)


def _stop(proc: subprocess.Popen) -> None:
    """End a process group this test started (`ray start --block` stops its node's processes on SIGTERM)."""
    for sig, wait in ((signal.SIGTERM, 20), (signal.SIGKILL, 10)):
        if proc.poll() is not None:
            return
        try:
            os.killpg(proc.pid, sig)
            proc.wait(wait)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            pass


def test_a_node_killed_mid_run_changes_nothing_in_the_submission(split, local, cluster, tmp_path):
    """A worker node dies (its raylet killed) while the run computes: its chunk's unfinished frames go to the
    other workers, the submission equals the local one and no frame is journaled twice."""
    c, workers = cluster
    out = tmp_path / "sub.zip"
    journal = out.with_name("sub.journal.jsonl")
    result: dict = {}

    def drive() -> None:
        try:
            result["res"] = run_split(split, "val", METHOD, out, all_frames=True, progress=False,
                                      ray_address=c.address, ray_options=RayOptions(chunk_frames=8))
        except BaseException as e:  # handed to the test thread
            result["error"] = e

    driver = threading.Thread(target=drive)
    driver.start()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and driver.is_alive() and len(_keys(journal)) < 15:
        time.sleep(0.05)
    assert driver.is_alive(), f"the run ended before a node could be killed: {result}"
    c.remove_node(workers[0], allow_graceful=False)
    driver.join(180)
    assert not driver.is_alive() and "error" not in result, result.get("error")
    res = result["res"]
    assert res.cluster["nodes"] == 3 and res.cluster["requeued"] >= 1, res.cluster
    keys = _keys(journal)
    assert len(keys) == len(set(keys)) == TOTAL
    _same_outputs(local, out)


def test_bad_cluster_requests_are_clear_errors(split, tmp_path, capsys):
    """Options that cannot work are refused in one line before anything runs."""
    with pytest.raises(ValueError, match="--gpus-per-task must be >= 0"):
        RayOptions(gpus_per_task=-1)
    assert main(["run", str(split), "--method", METHOD, "-o", str(tmp_path / "a.zip"), "--gpus-per-task", "1"]) == 1
    assert "--gpus-per-task applies to a run on Ray: add --ray" in capsys.readouterr().err
    assert main(["run", str(split), "--method", METHOD, "-o", str(tmp_path / "a.zip"), "--ray", "--workers", "4"]) == 1
    assert "--workers sizes the local pool" in capsys.readouterr().err
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ClusterError, match=f"cannot reach the Ray cluster at 127.0.0.1:{port}"):
        run_split(split, "val", METHOD, tmp_path / "b.zip", progress=False, ray_address=f"127.0.0.1:{port}")
    from mapfree.methods import get

    # Which methods ask a cluster with GPUs for one per worker by default: those that run networks.
    assert not get("sift_pnp_sensor").networks and get("xfeat_pnp_sensor").networks
    assert get("mast3r_pnp_mast3r").networks
    nodes = [{"Resources": {"CPU": 4.0, "GPU": 1.0}}, {"Resources": {"CPU": 8.0}}]
    assert task_slots(nodes, 1, 0) == 12 and task_slots(nodes, 1, 0.25) == 4 and task_slots(nodes, 2, 1) == 1


def test_fractional_gpus_put_several_workers_on_one_gpu(split, local, cluster, tmp_path):
    """A node declaring one GPU (Ray schedules by declared resources; the method itself runs on the CPU here):
    --gpus-per-task 0.5 starts two workers there and none on the GPU-less nodes; the poses are the local ones."""
    c, _ = cluster
    c.add_node(num_cpus=2, num_gpus=1, object_store_memory=80 * MB)
    c.wait_for_nodes()
    out = tmp_path / "gpu-half.zip"
    res = run_split(split, "val", METHOD, out, all_frames=True, progress=False, scenes=["s00001"],
                    ray_address=c.address, ray_options=RayOptions(gpus_per_task=0.5))
    assert res.cluster["workers"] == 2 and res.cluster["nodes"] == 1, res.cluster
    with zipfile.ZipFile(local) as a, zipfile.ZipFile(out) as b:
        assert b.read("pose_s00001.txt") == a.read("pose_s00001.txt")
    # A method that runs networks asks for a whole GPU by default: one worker, on the GPU node.
    res = run_split(split, "val", "xfeat_pnp_sensor", tmp_path / "xfeat.zip", progress=False, scenes=["s00001"],
                    ray_address=c.address)
    assert res.computed == QUERIES // 5 and res.cluster["workers"] == 1 and res.cluster["tasks"] == 2, res.cluster

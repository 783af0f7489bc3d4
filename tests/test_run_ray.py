"""``mapfree run --ray`` on a real three-node Ray cluster on this machine: the same submission as a local run,
a lost node or a killed driver costs no frame and journals none twice, a node without the data is one clear line.

One cluster (``tests/raycluster.py``: a head and two worker nodes of one CPU each, in a process of its own)
serves the module; every run is a ``mapfree run`` process, as a user starts it. The split is synthetic (3 scenes
of 30 small queries) and the method SIFT + PnP, so a whole run takes seconds.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest

pytest.importorskip("ray")

from mapfree.data.synth import SynthOptions, generate
from mapfree.relocalize import read_journal, run_split
from mapfree.relocalize.distributed import ClusterError, RayOptions, task_slots
from raycluster import ENV

pytestmark = pytest.mark.slow

METHOD = "sift_pnp_sensor"
SCENES, QUERIES = 3, 30
TOTAL = SCENES * QUERIES  # --all-frames
KEEPER = Path(__file__).with_name("raycluster.py")


class Keeper:
    """The cluster's process: its address, its Ray Client address, and commands (``kill I``, ``add_gpu``)."""

    def __init__(self, workers: int = 2, token: str | None = None) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(KEEPER), "cluster", str(workers)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
            env={**os.environ, **ENV, **({"RAY_AUTH_TOKEN": token} if token else {})},
        )
        info = json.loads(self._line(lambda s: s.startswith("{")))
        self.address, self.client, self.workers = info["address"], info["client"], info["workers"]

    def _line(self, want) -> str:
        for line in self.proc.stdout:  # Ray may print lines of its own
            if want(line.strip()):
                return line.strip()
        raise RuntimeError(f"the cluster process ended (exit {self.proc.wait()})")

    def command(self, cmd: str) -> None:
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()
        self._line(lambda s: s == "ok")

    def stop(self) -> None:
        self.proc.stdin.close()
        try:
            self.proc.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)


@pytest.fixture(scope="module")
def split(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ray-split")
    generate(
        root, "val", SCENES, QUERIES, options=SynthOptions(width=320, height=240, write_mono=False), progress=False
    )
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
    keeper = Keeper()
    try:
        yield keeper
    finally:
        keeper.stop()


def mapfree_run(
    split: Path, out: Path, *args: str, popen: bool = False, as_json: bool = True, env: dict[str, str] | None = None
):
    """``mapfree run SPLIT --method METHOD -o OUT --no-progress [--json] ARGS`` as its own process."""
    cmd = [
        sys.executable,
        "-m",
        "mapfree",
        "run",
        str(split),
        "--method",
        METHOD,
        "-o",
        str(out),
        "--no-progress",
        *(["--json"] if as_json else []),
        *args,
    ]
    env = {**os.environ, **ENV, **(env or {})}
    if popen:
        return subprocess.Popen(
            cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env
        )
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)


def frame_workers(ancestor: int) -> list[int]:
    """The ``ray::FrameWorker`` processes descending from process ``ancestor`` (Linux ``/proc``)."""
    parents, titles = {}, {}
    for d in Path("/proc").iterdir():
        try:
            stat = (d / "stat").read_text()
            titles[int(d.name)] = (d / "cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
        except (ValueError, OSError):
            continue
        parents[int(d.name)] = int(stat.rsplit(")", 1)[1].split()[1])

    def descends(pid: int) -> bool:
        while pid > 1:
            pid = parents.get(pid, 0)
            if pid == ancestor:
                return True
        return False

    return [p for p, t in titles.items() if t.startswith("ray::FrameWorker") and descends(p)]


def summary(done: subprocess.CompletedProcess) -> dict:
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def _same_outputs(a: Path, b: Path) -> None:
    assert a.read_bytes() == b.read_bytes()
    fa, fb = (p.with_name(p.stem + ".failures.jsonl") for p in (a, b))
    assert fa.read_text() == fb.read_text()


def _keys(journal: Path) -> list[tuple[str, str]]:
    return [(r["scene"], r["frame"]) for r in read_journal(journal)[1]]


def _scene_file(zip_path: Path, scene: str) -> bytes:
    with zipfile.ZipFile(zip_path) as z:
        return z.read(f"pose_{scene}.txt")


def test_three_nodes_write_the_local_submission_byte_for_byte(split, local, cluster, tmp_path):
    out = tmp_path / "sub.zip"
    res = summary(mapfree_run(split, out, "--all-frames", "--ray", cluster.address))
    assert res["computed"] == TOTAL and res["cluster"]["nodes"] == 3 and res["cluster"]["workers"] == 3
    assert res["cluster"]["requeued"] == 0
    if Path("/proc/self/stat").exists():  # the run's workers ended with it (one outlived it by seconds)
        assert frame_workers(cluster.proc.pid) == []
    _same_outputs(local, out)
    keys = _keys(out.with_name("sub.journal.jsonl"))
    assert len(keys) == len(set(keys)) == TOTAL
    # A GPU per worker on a cluster without GPUs: refused at once, naming what the nodes hold.
    done = mapfree_run(split, tmp_path / "gpu.zip", "--ray", cluster.address, "--gpus-per-task", "1")
    assert (
        done.returncode == 1 and "no node of the Ray cluster has room for a worker of 1 CPU(s) and 1 GPU" in done.stderr
    ), done.stderr
    # A finished run resumed: nothing to compute, the cluster is not even reached.
    again = run_split(split, "val", METHOD, out, all_frames=True, progress=False, resume=True, ray_address="ray://x:1")
    assert again.computed == 0 and again.skipped == TOTAL and again.cluster == {}


def test_multi_frame_track_and_figures_equal_the_local_ones(split, cluster, tmp_path):
    """--track multi --viz --ray ADDRESS: the fused submission and every figure equal a local run's."""
    for where, extra in (("local", []), ("ray", ["--ray", cluster.address])):
        done = mapfree_run(
            split,
            tmp_path / where / "m.zip",
            "--track",
            "multi",
            "--scenes",
            "s00001",
            "--viz",
            str(tmp_path / where / "viz"),
            *extra,
        )
        assert summary(done)["frames"]["computed"] == 3 * 9  # 30 queries: 3 bursts of 9 frames
    _same_outputs(tmp_path / "local/m.zip", tmp_path / "ray/m.zip")
    assert (tmp_path / "local/m.frames.zip").read_bytes() == (tmp_path / "ray/m.frames.zip").read_bytes()
    figures = sorted(p.relative_to(tmp_path / "local/viz") for p in (tmp_path / "local/viz").rglob("*.jpg"))
    assert len(figures) == 3 * 9
    assert figures == sorted(p.relative_to(tmp_path / "ray/viz") for p in (tmp_path / "ray/viz").rglob("*.jpg"))
    for f in figures:
        assert (tmp_path / "local/viz" / f).read_bytes() == (tmp_path / "ray/viz" / f).read_bytes(), f
    text = mapfree_run(
        split, tmp_path / "ray/m.zip", "--track", "multi", "--scenes", "s00001", "--resume", as_json=False
    )
    assert text.returncode == 0 and "(0 computed, 27 from the journal" in text.stdout, text.stdout + text.stderr


def test_k_references_the_same_on_the_cluster(realmini, cluster, tmp_path):
    """--references 2 (DenseVLAD retrieval among posed mapping images): the workers choose and retrieve the
    references as a local run does, so the submission is the same bytes."""
    from realmini_layouts import mapfree_multi_reference_scene

    root = mapfree_multi_reference_scene(realmini, tmp_path / "data")
    local_out = tmp_path / "local.zip"
    done = mapfree_run(root, local_out, "--references", "2", "--all-frames")
    res = summary(
        mapfree_run(root, tmp_path / "ray.zip", "--references", "2", "--all-frames", "--ray", cluster.address)
    )
    assert res["computed"] == summary(done)["computed"] > 0 and res["cluster"]["workers"] >= 1
    _same_outputs(local_out, tmp_path / "ray.zip")


def test_through_ray_client_the_same_poses(split, local, cluster, tmp_path):
    """A driver outside the cluster (--ray ray://HOST:PORT, Ray Client: chunks come back whole, not streamed)."""
    out = tmp_path / "client.zip"
    for _ in range(2):  # Ray Client's per-client server, forked by its proxy, now and then dies as it starts
        done = mapfree_run(split, out, "--all-frames", "--scenes", "s00002", "--ray", cluster.client)
        if "Initialization failure from server" not in done.stderr:
            break
    res = summary(done)
    assert res["computed"] == QUERIES and res["cluster"]["workers"] == 3
    assert _scene_file(out, "s00002") == _scene_file(local, "s00002")


def test_resume_after_the_driver_is_killed_computes_only_the_missing_frames(split, local, cluster, tmp_path):
    out = tmp_path / "sub.zip"
    journal = out.with_name("sub.journal.jsonl")
    proc = mapfree_run(split, out, "--all-frames", "--ray", cluster.address, popen=True)
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

    res = summary(mapfree_run(split, out, "--all-frames", "--resume", "--ray", cluster.address))
    after = read_journal(journal)[1]
    keys = [(r["scene"], r["frame"]) for r in after]
    assert len(keys) == len(set(keys)) == TOTAL  # nothing lost, nothing journaled twice
    assert res["skipped"] == len(before) and res["computed"] == TOTAL - len(before)
    assert after[: len(before)] == before
    _same_outputs(local, out)


def test_ctrl_c_stops_the_cluster_run_and_resume_finishes_it(split, local, cluster, tmp_path):
    """Ctrl-C in the driver: one line saying how many frames are kept (exit 130, no traceback) within seconds,
    the workers stop, and --resume computes only the rest: the same ZIP as the local run, no frame twice."""
    out = tmp_path / "sub.zip"
    journal = out.with_name("sub.journal.jsonl")
    proc = mapfree_run(split, out, "--all-frames", "--ray", cluster.address, popen=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None and len(_keys(journal)) < 10:
            time.sleep(0.05)
        assert proc.poll() is None, f"the run ended before Ctrl-C: {proc.stderr.read()}"
        os.killpg(proc.pid, signal.SIGINT)  # what a terminal sends to the foreground process group
        t0 = time.monotonic()
        proc.wait(60)
        stopped_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    err = proc.stderr.read()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err and "--resume" in err, err
    assert stopped_s < 30
    before = read_journal(journal)[1]
    assert 10 <= len(before) < TOTAL and not out.exists()

    res = summary(mapfree_run(split, out, "--all-frames", "--resume", "--ray", cluster.address))
    keys = _keys(journal)
    assert len(keys) == len(set(keys)) == TOTAL
    assert res["computed"] == TOTAL - len(before)
    _same_outputs(local, out)


def test_weights_missing_on_the_nodes_stop_the_run_before_any_work(split, cluster, tmp_path):
    """SuperGlue's weights are on no node (nor downloadable here): each worker builds the method on its node, and
    the first to fail ends the run in one line naming its node and where the weights go; nothing is journaled."""
    out = tmp_path / "sg.zip"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapfree",
            "run",
            str(split),
            "--method",
            "superglue_pnp_sensor",
            "-o",
            str(out),
            "--no-progress",
            "--scenes",
            "s00000",
            "--ray",
            cluster.address,
        ],
        capture_output=True,
        text=True,
        env={**os.environ, **ENV},
    )
    err = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(err) == 1 and "cannot run method 'superglue_pnp_sensor'" in err[0], err
    assert f"node 127.0.0.1 ({socket.gethostname()}, node " in err[0] and "$MAPFREE_WEIGHTS_DIR" in err[0], err
    assert not read_journal(out.with_name("sg.journal.jsonl"))[1] and not out.exists()


def test_a_node_that_cannot_read_the_dataset_is_one_clear_line(split, cluster, tmp_path):
    """A node whose mount namespace hides the dataset root (as a machine without the shared storage mounted):
    the run fails before any work, naming that node and the root; no frame is journaled."""
    if shutil.which("unshare") is None or subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode:
        pytest.skip("needs mount namespaces (unshare -m) to hide the dataset from one node")
    empty = tmp_path / "empty"
    empty.mkdir()
    start = f'mount --bind "{empty}" "{split}" && exec "{sys.executable}" "{KEEPER}" node "$0"'
    node = subprocess.Popen(
        ["unshare", "-m", "--propagation", "private", "sh", "-c", start, cluster.address],
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env={**os.environ, **ENV},
    )
    out = tmp_path / "sub.zip"
    try:
        blind = node.stdout.readline().strip()
        assert blind, f"the node without the dataset did not start (exit {node.poll()})"
        done = mapfree_run(split, out, "--all-frames", "--ray", cluster.address)
        err = done.stderr.strip().splitlines()
        assert done.returncode == 1 and len(err) == 1, done.stderr
        assert f"node {blind[:8]})" in err[0] and f"cannot read the dataset root {split}" in err[0], err[0]
        assert not read_journal(out.with_name("sub.journal.jsonl"))[1] and not out.exists()
    finally:
        _stop(node)


def _stop(proc: subprocess.Popen) -> None:
    """End a process group this test started (the node stops its processes on SIGTERM)."""
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
    out = tmp_path / "sub.zip"
    journal = out.with_name("sub.journal.jsonl")
    proc = mapfree_run(split, out, "--all-frames", "--ray", cluster.address, popen=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None and len(_keys(journal)) < 15:
            time.sleep(0.05)
        assert proc.poll() is None, f"the run ended before a node could be killed: {proc.stderr.read()}"
        cluster.command("kill 0")
        err = proc.communicate(timeout=180)[1]
    finally:
        _stop(proc)
    assert proc.returncode == 0, err
    assert "lost the worker on node" in err and "go to another worker" in err, err
    keys = _keys(journal)
    assert len(keys) == len(set(keys)) == TOTAL
    _same_outputs(local, out)


def test_fractional_gpus_put_several_workers_on_one_gpu(split, local, cluster, tmp_path):
    """A node declaring one GPU (Ray schedules by declared resources; the method itself runs on the CPU here):
    --gpus-per-task 0.5 starts two workers there and none on the GPU-less nodes; the poses are the local ones."""
    cluster.command("add_gpu")
    out = tmp_path / "gpu-half.zip"
    res = summary(
        mapfree_run(
            split, out, "--all-frames", "--scenes", "s00001", "--ray", cluster.address, "--gpus-per-task", "0.5"
        )
    )
    assert res["cluster"]["workers"] == 2 and res["cluster"]["nodes"] == 1, res["cluster"]
    assert _scene_file(out, "s00001") == _scene_file(local, "s00001")
    # A method that runs networks asks for a whole GPU by default: one worker, on the GPU node.
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapfree",
            "run",
            str(split),
            "--method",
            "xfeat_pnp_sensor",
            "-o",
            str(tmp_path / "xfeat.zip"),
            "--scenes",
            "s00001",
            "--no-progress",
            "--json",
            "--ray",
            cluster.address,
        ],
        capture_output=True,
        text=True,
        env={**os.environ, **ENV},
    )
    res = summary(done)
    assert res["computed"] == QUERIES // 5 and res["cluster"]["workers"] == 1 and res["cluster"]["tasks"] == 2, res


def test_bad_cluster_requests_are_clear_errors(split, tmp_path, capsys):
    """Options that cannot work are refused in one line before anything runs."""
    from mapfree.cli import main
    from mapfree.methods import get

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
    # Which methods ask a cluster with GPUs for one per worker by default: those that run networks.
    assert not get("sift_pnp_sensor").networks and get("xfeat_pnp_sensor").networks
    assert get("mast3r_pnp_mast3r").networks
    nodes = [{"Resources": {"CPU": 4.0, "GPU": 1.0}}, {"Resources": {"CPU": 8.0}}]
    assert task_slots(nodes, 1, 0) == 12 and task_slots(nodes, 1, 0.25) == 4 and task_slots(nodes, 2, 1) == 1


def test_a_cluster_that_wants_a_token_says_so_and_takes_it(split, tmp_path):
    """Ray's token authentication (on by default for clusters started where a token exists): a driver without
    the token heard "cannot reach the Ray cluster", as if the network were at fault."""
    keeper = Keeper(workers=0, token="s3cret-of-the-cluster")
    try:
        home = {"HOME": str(tmp_path), "RAY_AUTH_TOKEN": ""}  # no ~/.ray/auth_token, no token in the environment
        for extra, why in (
            ({}, "RAY_AUTH_MODE is not 'token' here, so no token was sent"),
            ({"RAY_AUTH_MODE": "token"}, "this machine has no token"),
        ):
            done = mapfree_run(
                split, tmp_path / "a.zip", "--ray", keeper.address, "--scenes", "s00000", env={**home, **extra}
            )
            assert done.returncode == 1 and done.stderr.splitlines() == [
                f"mapfree run: error: the Ray cluster at {keeper.address} refused this driver: it uses token "
                f"authentication and {why}: run with RAY_AUTH_MODE=token and the cluster's token (`ray get-auth-token` "
                "on the head prints it) in RAY_AUTH_TOKEN or ~/.ray/auth_token"
            ], done.stderr
        token = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": "s3cret-of-the-cluster"}
        res = summary(mapfree_run(split, tmp_path / "b.zip", "--ray", keeper.address, "--scenes", "s00000", env=token))
        assert res["computed"] == QUERIES // 5
    finally:
        keeper.stop()

"""Shared fixtures. Engineers: only ADD fixtures here."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
# One BLAS / OpenMP thread per test process (and the processes tests start): on CI's 2 shared cores a second thread
# only spins while it waits, and numpy's OpenBLAS then runs a K-means or a large matrix product 10x slower (a
# DenseVLAD vocabulary: 4 s with one thread, 50 s with two under load). Set the variables to override.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
# Ray (mapfree build --ray) binds to the loopback address only: tests never send traffic to another address.
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")


def _shared(rel: str, marker: str) -> Path:
    """``shared/REL`` beside the checkout (or at /work/shared), holding ``marker``; the test fails without it."""
    for cand in (Path(__file__).resolve().parents[2] / "shared" / rel, Path("/work/shared") / rel):
        if (cand / marker).exists():
            return cand
    pytest.fail(f"shared/{rel} not found beside the checkout")


@pytest.fixture(scope="session")
def realmini() -> Path:
    """Root of the real-image sample split (val/s00000..s00003, depth suffix ``sensor``)."""
    return _shared("data/realmini-dev", "val")


@pytest.fixture
def one_torch_thread():
    """One intra-op thread: the CI machine's cores are shared, and spinning thread pools slow tiny nets 50x.
    ``MAPFREE_TEST_TORCH_THREADS`` sets another count (bench/kernel_spread.py measures the fixtures' spread with 2)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(int(os.environ.get("MAPFREE_TEST_TORCH_THREADS", "1")))
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def official_rpr() -> Path:
    """Folder with official_rpr.json: the public RPR networks' outputs on fill-rule weights (README.md there)."""
    return _shared("fixtures/official-rpr", "official_rpr.json")


@pytest.fixture(scope="session")
def mast3r_fixture() -> Path:
    """Folder with mast3r.json / mast3r_outputs.npz: the public MASt3R/DUSt3R outputs on fill-rule weights."""
    return _shared("fixtures/mast3r", "mast3r.json")


@pytest.fixture(scope="session")
def mickey_fixture() -> Path:
    """Folder with mickey.json / mickey_outputs.npz: the public MicKey network and solver on fill-rule weights."""
    return _shared("fixtures/mickey", "mickey.json")


@pytest.fixture(scope="session")
def synth_val(tmp_path_factory) -> Path:
    """A small synthetic val split, read-only (copy it to change it): two scenes of 10 queries at 240x320, sensor
    depth only (suffix ``sensor``)."""
    from mapfree.cli import main

    root = tmp_path_factory.mktemp("synth-val")
    assert (
        main(
            [
                "synth",
                str(root),
                "--split",
                "val",
                "--scenes",
                "2",
                "--queries",
                "10",
                "--size",
                "240x320",
                "--no-mono",
                "--quiet",
            ]
        )
        == 0
    )
    return root


@pytest.fixture(scope="module")
def synth(synth_val) -> Path:
    """A small synthetic val split: two scenes of 10 queries, sensor depth (suffix ``sensor``); read-only."""
    return synth_val


@pytest.fixture(scope="session")
def dune_fixture() -> Path:
    """Folder with dune_mast3r.json / dune_mast3r_outputs.npz: the public DUNE-MASt3R outputs on fill-rule weights."""
    return _shared("fixtures/dune-mast3r", "dune_mast3r.json")


# `make test` runs the suite on two pytest-xdist workers. Each test file stays on one worker, so its module fixtures
# (an ONNX export, a network built once) are made once; the service tests share one worker (their servers are
# session fixtures) and so do the files that start Ray clusters.
_GROUPS = {"tests/test_build.py": "ray", "tests/test_run_ray.py": "ray"}


def worker_group(nodeid: str) -> str:
    """The worker group of a test: ``service``, ``ray`` or its file."""
    path = nodeid.split("::", 1)[0]
    return "service" if path.startswith("tests/service/") else _GROUPS.get(path, path)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    from xdist.scheduler import LoadScopeScheduling

    class ByGroup(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return worker_group(nodeid)

    return ByGroup(config, log)

"""What one API process keeps for relocalization, and how it is shared: the pool of built methods (bounded in
bytes, shared by equal configurations), the prepared-anchor cache and the heavy threads (a fair share per
account). In-process, with real SIFT relocalizers on realmini-dev photos."""

from __future__ import annotations

import pytest

from mapfree.data import Dataset


@pytest.fixture(scope="module")
def pair(realmini_dir):
    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")
    return ref.image(), ref.intrinsics, ref.depth("sensor"), query.image(), query.intrinsics, query.depth("sensor")


def test_a_depth_suffix_no_request_can_carry_is_refused_before_anything_is_built():
    from mapfree.service.anchors.localizers import check_method
    from mapfree.service.inputs import UploadError

    for name in ("disk-lightglue_pnp_d1", "aliked-lightglue_pnp_zz1", "sift_pnp_d10"):
        with pytest.raises(UploadError) as e:
            check_method(name)
        assert e.value.status == 422 and "uploaded with the photo" in e.value.message
    assert check_method("sift_pnp_mono") == "sift_pnp_mono"
    assert check_method("sift_emat_none") == "sift_emat_none"


def test_method_names_share_a_pool_bounded_in_bytes(pair):
    """Three names of one configuration build one relocalizer; three configurations over a budget of one keep
    one (the most recent), and every answer is the same as before the others came."""
    from mapfree.service.anchors.localizers import Localizers

    ref_img, ref_K, ref_d, q_img, q_K, q_d = pair
    locs = Localizers(per_method=1, pool_bytes=1 << 30)
    poses = [
        locs.localize(f"a{i}", name, ref_img, ref_K, ref_d, q_img, q_K).pose
        for i, name in enumerate(("sift_pnp_sensor", "sift_pnp_mono", "sift_pnp_dptkitti"))
    ]
    assert locs.pool.built == 1 and locs.pool.configs() == 1
    assert all(p is not None for p in poses)

    small = Localizers(per_method=1, pool_bytes=1)  # room for less than one: the most recent is kept
    for name in ("sift_pnp_sensor", "sift_emat_sensor", "sift_procrustes_sensor", "sift_pnp_sensor"):
        est = small.localize("b", name, ref_img, ref_K, ref_d, q_img, q_K, q_d)  # query depth: each solver runs
        assert est.pose is not None, (name, est.reason)
        assert small.pool.configs() == 1
    assert small.pool.built == 4  # sift_pnp_sensor was dropped and built again


def test_one_account_cannot_evict_everyone_elses_prepared_anchors(pair):
    """A cache with room for two and a half anchors: one account localizing four anchors round-robin used to
    evict everyone's (every localize then prepared its anchor again); now it evicts its own, and another
    account's anchor is answered from the cache throughout."""
    from mapfree.service.anchors.localizers import Localizers, Photo

    ref_img, ref_K, ref_d, q_img, q_K, _ = pair
    probe = Localizers(per_method=1)
    probe.localize("x", "sift_pnp_sensor", ref_img, ref_K, ref_d, q_img, q_K)
    one = probe.anchors.total  # bytes of one prepared anchor
    locs = Localizers(per_method=1, cache_bytes=int(2.5 * one))

    def photos():
        return [Photo(ref_img, ref_K, ref_d)]

    def unprepared():
        raise AssertionError("the victim's anchor was evicted and prepared again")

    locs.localize_photos("victim", "sift_pnp_sensor", (), photos, q_img, q_K, owner="victim")
    for _ in range(2):
        for i in range(4):
            locs.localize_photos(f"attacker{i}", "sift_pnp_sensor", (), photos, q_img, q_K, owner="attacker")
            est = locs.localize_photos("victim", "sift_pnp_sensor", (), unprepared, q_img, q_K, owner="victim")
            assert est.pose is not None
    assert locs.anchors.owned("victim") == one and locs.anchors.total <= 2.5 * one


def test_heavy_threads_are_shared_fairly_between_accounts():
    """One thread: an account with four requests in, then another's one request. The other's used to wait
    behind all four; now it runs second (turns go round the accounts), and the first account's fifth request
    is refused with 429 (its share: half the room) while others still get in."""
    import asyncio
    import time

    from fastapi import HTTPException

    from mapfree.service.http.heavy import HeavyPool

    pool = HeavyPool(threads=1, queue=8)
    finished: list[str] = []

    def work(name: str) -> None:
        time.sleep(0.15)
        finished.append(name)

    async def scenario() -> int:
        flood = [asyncio.create_task(pool.run(work, f"a{i}", account="a")) for i in range(4)]
        await asyncio.sleep(0.01)
        try:
            await pool.run(work, "a5", account="a")
            refused = 0
        except HTTPException as e:
            refused = e.status_code
        other = asyncio.create_task(pool.run(work, "b", account="b"))
        await asyncio.gather(*flood, other)
        return refused

    assert asyncio.run(scenario()) == 429
    assert finished == ["a0", "b", "a1", "a2", "a3"]
    assert pool.admitted == 0 and pool.running == 0
    pool.shutdown()


@pytest.mark.parametrize("accounts", [2, 3, 4])
def test_heavy_share_holds_against_several_accounts_flooding(accounts):
    """``accounts`` accounts each keep retrying to hold 10 requests in (4 threads, 8 waiting: 12 in all). Two
    used to hold all 12 (a share was half the room whatever their number), and a newcomer got 429 after 429.
    Now, once the flood runs, each holds at most 12 // (k + 1) and a newcomer's five requests in a row are
    all admitted and answered."""
    import asyncio
    import time

    from fastapi import HTTPException

    from mapfree.service.http.heavy import HeavyPool

    pool = HeavyPool(threads=4, queue=8)
    held: dict[str, int] = {}
    most: dict[str, int] = {}

    def work(name: str) -> str:
        time.sleep(0.02)
        return name

    async def one(name: str) -> None:
        held[name] = held.get(name, 0) + 1
        try:
            await pool.run(work, name, account=name)
        finally:
            held[name] -= 1

    async def flood(name: str, until: float) -> None:
        tasks: set[asyncio.Task] = set()
        while time.monotonic() < until:
            tasks = {t for t in tasks if not t.done()}
            if len(tasks) < 10:
                task = asyncio.create_task(one(name))
                await asyncio.sleep(0)
                if task.done() and isinstance(task.exception(), HTTPException):
                    await asyncio.sleep(0.002)
                else:
                    tasks.add(task)
            else:
                await asyncio.sleep(0.002)
        await asyncio.gather(*tasks, return_exceptions=True)

    async def scenario() -> list[int]:
        until = time.monotonic() + 1.2
        floods = [asyncio.create_task(flood(f"f{i}", until)) for i in range(accounts)]
        await asyncio.sleep(0.4)  # the flood has settled: every request in now came in under the rule
        answers = []
        for i in range(5):
            for name in held:
                most[name] = max(most.get(name, 0), held[name])
            try:
                assert await pool.run(work, f"new{i}", account="newcomer") == f"new{i}"
                answers.append(200)
            except HTTPException as e:
                answers.append(e.status_code)
        await asyncio.gather(*floods)
        return answers

    assert asyncio.run(scenario()) == [200] * 5
    assert max(most.values()) <= 12 // (accounts + 1), most
    assert pool.admitted == 0 and pool.running == 0
    pool.shutdown()


@pytest.mark.parametrize("accounts", [2, 3, 4])
def test_prepared_anchor_cache_keeps_a_newcomers_share_against_several_accounts(accounts):
    """``accounts`` accounts put anchors round-robin into a cache of 256 MiB, far more than fits; a newcomer's anchor
    of the stated share (``256 / (k + 1)`` MiB) is kept while they go on (the one holding the most loses, so the
    newcomer, holding less than each of them could, is never the one), and one a step larger is not: the bound is
    tight."""
    from mapfree.service.anchors.prepared import ByteLRU

    mib = 1 << 20

    def flood(lru: ByteLRU, rounds: int, start: int = 0) -> None:
        for i in range(start, start + rounds):
            for a in range(accounts):
                lru.put(("flood", a, i), object(), 8 * mib, owner=f"f{a}")

    share = 256 * mib // (accounts + 1)
    for size, kept in ((share, True), (share + 16 * mib, False)):
        lru = ByteLRU(256 * mib)
        flood(lru, 100)
        lru.put("newcomer's anchor", "prepared", size, owner="newcomer")
        flood(lru, 200, start=100)
        assert (lru.get("newcomer's anchor") == "prepared") is kept, (size / mib, lru.owned("newcomer"))
        assert lru.total <= lru.max_bytes


_THREADS_PROBE = """
import json, os, sys, threading
from mapfree.cli.serve import register, settings_from_args
from mapfree.service.http.heavy import HeavyPool
import argparse
p = argparse.ArgumentParser(); register(p.add_subparsers())
s = settings_from_args(p.parse_args(["serve", *sys.argv[1:]]))
if s.method_threads:  # torch loaded before the heavy threads start, else by the method after
    import torch
pool = HeavyPool(s.heavy_threads, 0, method_threads=s.method_threads)

def seen():
    import cv2, torch
    from threadpoolctl import threadpool_info
    return {
        "thread": threading.current_thread().name.split("_")[0],
        "cv2": cv2.getNumThreads(),
        "torch": torch.get_num_threads(),
        "apis": sorted({i["internal_api"] for i in threadpool_info()}),
        **{i["filepath"]: i["num_threads"] for i in threadpool_info()},
    }

print(json.dumps([pool.executor.submit(seen).result() for _ in range(2)] + [{"cpus": os.cpu_count()}]))
"""


@pytest.mark.parametrize("flags", [("--heavy-threads", "1"), ("--heavy-threads", "2", "--method-threads", "3")])
def test_the_heavy_threads_run_methods_with_the_configured_thread_counts(flags):
    """A server started with ``OMP_NUM_THREADS=1`` in its environment used to run NumPy's BLAS and torch on one
    thread and OpenCV on every core, whatever the library call it was compared with had. Each heavy thread now sets
    OpenCV, torch, the BLAS libraries and OpenMP to ``--method-threads`` when it starts (default: the CPUs divided
    among the heavy threads, so every CPU for a single heavy thread), torch loaded before or after."""
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-c", _THREADS_PROBE, *flags], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    *threads, cpus = json.loads(out.stdout.splitlines()[-1])
    want = 3 if "--method-threads" in flags else cpus["cpus"]
    for seen in threads:
        assert seen.pop("thread") == "mapfree-heavy"
        assert seen.pop("apis") == ["openblas", "openmp"], seen  # NumPy's and OpenCV's BLAS, torch's OpenMP
        assert set(seen.values()) == {want}, seen

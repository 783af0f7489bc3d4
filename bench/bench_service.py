"""Load test of `mapfree serve` on loopback (bounded), in phases, one table:

0. memory: three of those 38 MB submissions uploaded at once, then evaluated; the peak RSS (sampled every 20 ms)
   of the API process and of each worker process, separately, against their idle RSS: the workers parse the
   pose text piece by piece, so their growth stays a small multiple of the ZIP's size.
1. uploads: three streams each uploading a 38 MB submission (3 x 60 MB of pose lines each, within every limit)
   three times back to back (``--upload-rounds``), while the API process's memory (RSS, sampled every 20 ms)
   and `/health` latency (a dedicated client process polling every 10 ms, from the first upload to the last
   202) are measured against the idle API; targets: RSS < 400 MB and `/health` p99 < 100 ms. The workers then
   parse them.
2. 200 submissions from 20 concurrent clients with 4 evaluation workers, one worker SIGKILLed mid-run (every
   submission must end evaluated exactly once, none lost).
3. `localize` latency and throughput under 8 concurrent clients, against in-process localization.

Before / after phases (each against a server of this tree and one of ``--baseline``, a main checkout):
``photo``: peak API RSS while localizing one 4096x4096 query, then three at once (three methods);
``cache``: API RSS once three anchors of 16 photos of 4096x4096 are prepared;
``flood``: `/login` latency while 45 localize calls run at once.

Phases of this tree alone: ``overhead``: localize p50 / p95 against a cached anchor through the API and the same
call on the library in the same run (the default method and a SIFT preset; with ``--baseline``, the baseline
tree's API first, in the same run); ``pool``: API RSS while 100 distinct
method names create anchors, with the default method pool and a small one (and, with ``--baseline``, the
same names against the baseline tree).

    python bench/bench_service.py [--db postgresql://...] [--submissions 200] [--clients 20] [--workers 4]
                                  [--phases memory,uploads,submissions,localize] [--upload-rounds 3]
    python bench/bench_service.py --phases photo,cache,flood --baseline /tmp/mapfree-main
    python bench/bench_service.py --phases overhead,pool
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def realmini() -> Path:
    for c in (ROOT.parent / "shared/data/realmini-dev", Path("/work/shared/data/realmini-dev")):
        if (c / "val").is_dir():
            return c
    raise SystemExit("shared/data/realmini-dev not found")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def submission(split_dir: Path, rng: np.random.Generator) -> bytes:
    """GT poses plus noise: a valid, varied submission."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for scene in sorted(p for p in split_dir.iterdir() if p.is_dir()):
            lines = []
            for line in (scene / "poses.txt").read_text().splitlines():
                p = line.split()
                if len(p) == 8 and p[0].startswith("seq1/"):
                    t = np.array(p[5:], float) + rng.normal(scale=0.2, size=3)
                    lines.append(f"{p[0]} {' '.join(p[1:5])} {' '.join(f'{x:.6f}' for x in t)} {rng.uniform(1, 9):.3f}")
            z.writestr(f"pose_{scene.name}.txt", "\n".join(lines) + "\n")
    return buf.getvalue()


def big_submission(scenes: list[str], entry_bytes: int = 60_000_000) -> bytes:
    """A valid submission of ``entry_bytes`` of pose lines per scene (frames repeat: the reader keeps the first of
    each and reports the rest), about 4.7:1 compressible like real pose files: 3 scenes -> ~38 MB."""
    rng = np.random.default_rng(1)
    v = rng.normal(size=(20000, 4))
    block = "".join(
        f"seq1/frame_{i % 20:05d}.jpg 1.0 0.0 0.0 0.0 {r[0]:.4f} {r[1]:.4f} {r[2]:.4f} {abs(r[3]) * 10:.1f}\n"
        for i, r in enumerate(v)
    ).encode()
    text = (block * (entry_bytes // len(block) + 1))[:entry_bytes]
    text = text[: text.rfind(b"\n") + 1]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for s in scenes:
            z.writestr(f"pose_{s}.txt", text)
    return buf.getvalue()


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


def poll_health(url: str, interval: float, stop, out) -> None:
    """The dedicated /health client (its own process, so that the uploading threads' GIL does not inflate the
    figures): one keep-alive connection, a GET every ``interval`` s; sends (monotonic start, latency, status)."""
    samples = []
    with httpx.Client(base_url=url, timeout=30) as c:
        while not stop.is_set():
            t0 = time.monotonic()
            try:
                status = c.get("/health").status_code
            except httpx.HTTPError:
                status = 0
            samples.append((t0, time.monotonic() - t0, status))
            stop.wait(interval)
    out.put(samples)


def upload_pressure(url: str, api_pid: int, tokens: list[str], payload: bytes, rounds: int, interval: float) -> dict:
    """Three upload streams at once, each posting ``payload`` ``rounds`` times back to back; API RSS and /health
    latency (dedicated client process, every ``interval`` s) from the first upload to the last 202, and idle
    before."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    stop, out = ctx.Event(), ctx.Queue()
    poller = ctx.Process(target=poll_health, args=(url, interval, stop, out), daemon=True)
    poller.start()
    idle_rss = rss_mb(api_pid)
    time.sleep(2.0)  # the poller starts up (spawn) and measures the idle API
    done = threading.Event()
    rss = [idle_rss]

    def sample_rss() -> None:
        while not done.is_set():
            rss.append(rss_mb(api_pid))
            done.wait(0.02)

    def upload_stream(token: str) -> list[tuple[int, float, str]]:
        res = []
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=300) as c:
            for _ in range(rounds):
                t0 = time.perf_counter()
                r = c.post(
                    "/api/submissions", files={"file": ("big.zip", payload)}, data={"split": "val", "name": "big"}
                )
                res.append((r.status_code, time.perf_counter() - t0, r.json().get("id", r.text[:200])))
        return res

    sampler = threading.Thread(target=sample_rss)
    sampler.start()
    t_start = time.monotonic()
    with ThreadPoolExecutor(3) as ex:
        results = [r for stream in ex.map(upload_stream, tokens[:3]) for r in stream]
    t_end = time.monotonic()
    done.set()
    stop.set()
    sampler.join()
    samples = out.get(timeout=60)
    poller.join(30)
    during = [(dt, st) for t0, dt, st in samples if t_start <= t0 <= t_end]
    idle = [(dt, st) for t0, dt, st in samples if t0 < t_start][5:]  # past the connection's first requests
    return {
        "idle_rss": idle_rss,
        "max_rss": max(rss),
        "health": [dt for dt, _ in during],
        "health_bad": sum(st != 200 for _, st in during),
        "idle_health": [dt for dt, _ in idle],
        "uploads": results,
        "window": t_end - t_start,
    }


def worker_pids(serve_pid: int) -> list[int]:
    """The evaluation worker processes `mapfree serve` started (its children running the module
    mapfree.service.leaderboard.worker)."""
    pids = []
    for d in Path("/proc").iterdir():
        try:
            if (
                d.name.isdigit()
                and int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == serve_pid
                and b"mapfree.service.leaderboard.worker" in (d / "cmdline").read_bytes()
            ):
                pids.append(int(d.name))
        except (OSError, ValueError, IndexError):
            continue
    return sorted(pids)


def wait_evaluated(sessions, deadline: float, ids: list[str] | None = None, poll: float = 0.25) -> None:
    """Until no submission (of ``ids``; else none at all) is queued or running, or ``deadline`` (a busy SQLite
    database is asked again)."""
    from sqlalchemy import func, select
    from sqlalchemy.exc import OperationalError

    from mapfree.service.database.models import Submission

    pending = Submission.status.in_(("queued", "running"))
    if ids is not None:
        pending = pending & Submission.id.in_(ids)
    while time.time() < deadline:
        try:
            with sessions() as db:
                left = db.scalar(select(func.count()).select_from(Submission).where(pending))
        except OperationalError:
            continue
        if not left:
            return
        time.sleep(poll)


def upload_memory(url: str, api_pid: int, tokens: list[str], payload: bytes, sessions, deadline: float) -> dict:
    """Three uploads of ``payload`` at once, then their evaluation: peak RSS of the API process and of every
    worker process, sampled every 20 ms from before the uploads until the workers have parsed and scored them."""
    from mapfree.service.database.models import Submission

    workers = worker_pids(api_pid)
    pids = [api_pid, *workers]
    idle = {p: rss_mb(p) for p in pids}
    peak = dict(idle)
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            for p in pids:
                with contextlib.suppress(OSError, StopIteration):
                    peak[p] = max(peak[p], rss_mb(p))
            done.wait(0.02)

    def upload(token: str):
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=300) as c:
            r = c.post("/api/submissions", files={"file": ("big.zip", payload)}, data={"split": "val", "name": "mem"})
            return r.status_code, r.json().get("id")

    sampler = threading.Thread(target=sample)
    sampler.start()
    t0 = time.perf_counter()
    try:
        with ThreadPoolExecutor(3) as ex:
            results = list(ex.map(upload, tokens[:3]))
        ids = [i for code, i in results if code == 202]
        wait_evaluated(sessions, deadline, ids, poll=0.2)
    finally:
        done.set()
        sampler.join()
    with sessions() as db:
        statuses = [db.get(Submission, i).status for i in ids]
    return {
        "codes": [c for c, _ in results],
        "statuses": statuses,
        "wall": time.perf_counter() - t0,
        "api_idle": idle[api_pid],
        "api_peak": peak[api_pid],
        "worker_idle": max(idle[p] for p in workers),
        "worker_peak": max(peak[p] for p in workers),
        "workers": len(workers),
        "worker_peaks": sorted(peak[p] for p in workers),
    }


def pct(xs, q) -> float:
    return float(np.percentile(np.asarray(xs) * 1000, q)) if xs else float("nan")


# ------------------------------------------------------------------------------------------------------------
# Before / after phases of the relocalization API's memory and threads: each runs the same requests against a
# server started from the current code and from a baseline source tree (``--baseline``, e.g. a
# ``git worktree add --detach /tmp/mapfree-main main``), and prints both in one table.

MINE = {"photo", "cache", "flood"}
#: Phases of this tree alone (no baseline): API overhead over the library, and the bounded method pool.
OWN = {"overhead", "pool"}
RELOC_METHODS = ("sift_pnp_sensor", "sift_procrustes_sensor", "sift_emat_sensor")


def mem_available_mb() -> float:
    with open("/proc/meminfo") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("MemAvailable")) / 1024


class Serve:
    """``mapfree serve`` of one source tree (``code/src`` first on the path) on a fresh SQLite file, no workers,
    with accounts ``u0..u{n-1}``."""

    def __init__(self, code: Path, tmp: Path, data: Path, users: int = 3, extra: tuple[str, ...] = ()):
        self.tmp = Path(tempfile.mkdtemp(prefix="serve-", dir=tmp))
        self.env = {**os.environ, "PYTHONPATH": str(code / "src"), "OMP_NUM_THREADS": "1"}
        self.db = f"sqlite:///{self.tmp / 'bench.db'}"
        admin = [sys.executable, "-m", "mapfree.cli.admin", "--db", self.db, "create-user"]
        self.tokens = [
            subprocess.run([*admin, f"u{i}"], env=self.env, capture_output=True, text=True, check=True).stdout.split()[
                -1
            ]
            for i in range(users)
        ]
        self.url = f"http://127.0.0.1:{free_port()}"
        self.log = open(self.tmp / "serve.log", "w")  # noqa: SIM115 - the server writes it for as long as it runs
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "mapfree.cli.serve",
                "--db",
                self.db,
                "--data",
                str(data),
                "--workers",
                "0",
                "--port",
                self.url.rsplit(":", 1)[1],
                "--log-level",
                "warning",
                *extra,
            ],
            env=self.env,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        deadline = time.time() + 120
        while time.time() < deadline:
            try:
                if httpx.get(self.url + "/health", timeout=2).status_code < 500:
                    return
            except httpx.HTTPError:
                pass
            if self.proc.poll() is not None:
                break
            time.sleep(0.3)
        self.stop()
        raise SystemExit("server did not start:\n" + (self.tmp / "serve.log").read_text()[-2000:])

    def client(self, i: int = 0, timeout: float = 600) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers={"Authorization": f"Bearer {self.tokens[i]}"}, timeout=timeout)

    def rss(self) -> float:
        return rss_mb(self.proc.pid)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()


def peak_rss(pid: int, fn) -> tuple[float, float, object]:
    """(RSS before, peak RSS while ``fn()`` runs, its result), sampled every 20 ms."""
    before, peak, done = rss_mb(pid), [0.0], threading.Event()

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], rss_mb(pid))
            done.wait(0.02)

    t = threading.Thread(target=sample)
    t.start()
    try:
        out = fn()
    finally:
        done.set()
        t.join()
    return before, max(peak[0], before), out


def big_photo(frame, side: int, depth: bool = True):
    """A realmini frame upscaled to a ``side``-pixel long side (a phone photo): JPEG, uint16 depth PNG, form."""
    import cv2

    img = frame.image()
    h, w = img.shape[:2]
    s = side / max(h, w)
    nw, nh = round(w * s), round(h * s)
    jpg = cv2.imencode(
        ".jpg",
        cv2.cvtColor(cv2.resize(img, (nw, nh), interpolation=cv2.INTER_CUBIC), cv2.COLOR_RGB2BGR),
        [cv2.IMWRITE_JPEG_QUALITY, 90],
    )[1].tobytes()
    png = None
    if depth:
        d = cv2.imread(str(frame.depth_path("sensor")), cv2.IMREAD_UNCHANGED)
        png = cv2.imencode(".png", cv2.resize(d, (nw, nh), interpolation=cv2.INTER_NEAREST))[1].tobytes()
    K = frame.intrinsics.resized(nw, nh)
    return jpg, png, {"fx": repr(K.fx), "fy": repr(K.fy), "cx": repr(K.cx), "cy": repr(K.cy)}


def photo_phase(srv: Serve, scene, side: int, three: bool) -> dict:
    """Item 1: peak API RSS while localizing one ``side``-pixel query, then three at once (three methods,
    each with its own pool of relocalizers), against anchors of a ``side``-pixel photo."""
    ref_jpg, ref_png, ref_form = big_photo(scene.reference, side)
    q_jpg, _, q_form = big_photo(scene.frame("seq1/frame_00009.jpg"), side, depth=False)
    out: dict = {"idle": srv.rss()}
    anchors = []
    with srv.client() as c:
        for m in RELOC_METHODS:
            before, peak, r = peak_rss(
                srv.proc.pid,
                lambda m=m: c.post(
                    "/anchors",
                    files={"image": ("r.jpg", ref_jpg), "depth": ("d.png", ref_png)},
                    data={**ref_form, "method": m},
                ),
            )
            assert r.status_code == 201, r.text
            anchors.append(r.json()["id"])
            out["create"] = max(out.get("create", 0.0), peak)

    def localize(i: int):
        with srv.client(i) as c:
            r = c.post(f"/anchors/{anchors[i]}/localize", files={"image": ("q.jpg", q_jpg)}, data=q_form)
            return r.status_code, (r.json().get("ok") if r.status_code == 200 else r.text[:100])

    out["before_one"], out["one"], res = peak_rss(srv.proc.pid, lambda: localize(0))
    out["one_ok"] = res
    if three:
        with ThreadPoolExecutor(3) as ex:
            out["before_three"], out["three"], res = peak_rss(srv.proc.pid, lambda: list(ex.map(localize, range(3))))
        out["three_ok"] = res
    return out


def cache_phase(srv: Serve, scene, side: int, photos: int, anchors: int) -> dict:
    """Item 2: API RSS once ``anchors`` anchors of ``photos`` ``side``-pixel photos each are prepared (localized
    against once), and the peak while preparing them."""
    frames = [scene.reference] + [f for f in scene.queries][: photos - 1]
    ups = [big_photo(f, side) for f in frames]
    q_jpg, _, q_form = big_photo(scene.frame("seq1/frame_00009.jpg"), 720, depth=False)
    out = {"idle": srv.rss(), "peak": 0.0}
    ids = []
    with srv.client() as c:
        for _ in range(anchors):
            jpg, png, form = ups[0]
            r = c.post(
                "/anchors",
                files={"image": ("r.jpg", jpg), "depth": ("d.png", png)},
                data={**form, "method": "sift_pnp_sensor"},
            )
            assert r.status_code == 201, r.text
            aid = r.json()["id"]
            for f, (jpg, png, form) in zip(frames[1:], ups[1:]):
                q, t = f.pose.qt()
                pose = " ".join(f"{x:.9f}" for x in (*q, *t))
                r = c.post(
                    f"/anchors/{aid}/photos",
                    files={"image": ("p.jpg", jpg), "depth": ("d.png", png)},
                    data={**form, "pose": pose},
                )
                assert r.status_code == 201, r.text
            ids.append(aid)
        for aid in ids:
            _, peak, r = peak_rss(
                srv.proc.pid,
                lambda aid=aid: c.post(f"/anchors/{aid}/localize", files={"image": ("q.jpg", q_jpg)}, data=q_form),
            )
            assert r.status_code == 200, r.text
            out["peak"] = max(out["peak"], peak)
    out["after"] = srv.rss()
    return out


def flood_phase(srv: Serve, scene, calls: int) -> dict:
    """Item 6: ``/login`` latency (one client, a request every 50 ms) while ``calls`` localize calls of a
    1440x1920 query run at once; how the calls were answered."""
    ref = scene.reference
    jpg, png, form = big_photo(ref, 720)
    q_jpg, _, q_form = big_photo(scene.frame("seq1/frame_00009.jpg"), 1920, depth=False)
    with srv.client() as c:
        r = c.post(
            "/anchors",
            files={
                "image": ("r.jpg", ref.image_path.read_bytes()),
                "depth": ("d.png", ref.depth_path("sensor").read_bytes()),
            },
            data={**form, "method": "sift_pnp_sensor"},
        )
        assert r.status_code == 201, r.text
        aid = r.json()["id"]
    stop, lat = threading.Event(), []

    def poll() -> None:
        with httpx.Client(base_url=srv.url, timeout=120) as c:
            c.get("/login")
            while not stop.is_set():
                t0 = time.perf_counter()
                c.get("/login")
                lat.append(time.perf_counter() - t0)
                stop.wait(0.05)

    def localize(_):
        with srv.client(1) as c:
            return c.post(f"/anchors/{aid}/localize", files={"image": ("q.jpg", q_jpg)}, data=q_form).status_code

    poller = threading.Thread(target=poll)
    poller.start()
    time.sleep(1.0)
    idle = list(lat)
    t0 = time.perf_counter()
    with ThreadPoolExecutor(calls) as ex:
        codes = list(ex.map(localize, range(calls)))
    wall = time.perf_counter() - t0
    stop.set()
    poller.join()
    during = lat[len(idle) :]
    return {"idle": idle, "during": during, "codes": codes, "wall": wall}


def bench_data(prefix: str):
    """(a fresh folder holding a tiny synthetic val split for ``--data``, realmini-dev's scene s00000)."""
    from mapfree.data import Dataset
    from mapfree.data.synth import SynthOptions, generate

    tmp = Path(tempfile.mkdtemp(prefix=prefix))
    generate(
        tmp / "data",
        "val",
        1,
        2,
        seed=3,
        options=SynthOptions(first_scene=460, width=135, height=180, texture_size=128, write_mono=False),
        progress=False,
    )
    return tmp, Dataset(realmini()).scene("val", "s00000")


def before_after(a, phases: set[str]) -> list[tuple[str, str, str, str]]:
    """Run the chosen phases on the baseline tree and on this one -> table rows (what, baseline, now, note)."""
    tmp, scene = bench_data("bench-service-ba-")
    trees = {"baseline": Path(a.baseline).resolve(), "now": ROOT}
    res: dict[str, dict] = {}
    for label, code in trees.items():
        r = res[label] = {}
        if "photo" in phases:
            srv = Serve(code, tmp, tmp / "data")
            try:
                three = label == "now" or mem_available_mb() > a.min_free_mb
                r["photo"] = photo_phase(srv, scene, a.side, three)
            finally:
                srv.stop()
        if "cache" in phases:
            srv = Serve(code, tmp, tmp / "data")
            try:
                r["cache"] = cache_phase(srv, scene, a.side, a.anchor_photos, 3)
            finally:
                srv.stop()
        if "flood" in phases:
            srv = Serve(code, tmp, tmp / "data")
            try:
                r["flood"] = flood_phase(srv, scene, a.flood_calls)
            finally:
                srv.stop()
    b, n = res["baseline"], res["now"]
    mb = lambda x: f"{x:.0f}" if x else "-"  # noqa: E731
    rows = []
    if "photo" in phases:
        p, q = b["photo"], n["photo"]
        rows += [
            ("API RSS idle (MB)", mb(p["idle"]), mb(q["idle"]), ""),
            (f"peak RSS creating 3 anchors of a {a.side}² photo (MB)", mb(p["create"]), mb(q["create"]), ""),
            (
                f"peak RSS, one {a.side}² localize (MB)",
                mb(p["one"]),
                mb(q["one"]),
                f"from {mb(p['before_one'])} / {mb(q['before_one'])}; answers {p['one_ok']} / {q['one_ok']}",
            ),
            (
                f"peak RSS, three {a.side}² localize at once (MB)",
                mb(p.get("three")),
                mb(q.get("three")),
                "three methods" + ("" if "three" in p else f"; baseline skipped: under {a.min_free_mb} MB free"),
            ),
        ]
    if "cache" in phases:
        p, q = b["cache"], n["cache"]
        rows += [
            (
                f"API RSS after preparing 3 anchors of {a.anchor_photos} {a.side}² photos (MB)",
                mb(p["after"]),
                mb(q["after"]),
                f"idle {mb(p['idle'])} / {mb(q['idle'])}",
            ),
            ("peak RSS while preparing them (MB)", mb(p["peak"]), mb(q["peak"]), ""),
        ]
    if "flood" in phases:
        p, q = b["flood"], n["flood"]
        code = lambda f: ", ".join(f"{c} x {f['codes'].count(c)}" for c in sorted(set(f["codes"])))  # noqa: E731
        rows += [
            (
                f"/login p50 / max during {a.flood_calls} localize calls (ms)",
                f"{pct(p['during'], 50):.0f} / {pct(p['during'], 100):.0f}",
                f"{pct(q['during'], 50):.0f} / {pct(q['during'], 100):.0f}",
                f"idle p50 {pct(p['idle'], 50):.0f} / {pct(q['idle'], 50):.0f} ms",
            ),
            (
                f"the {a.flood_calls} localize calls (status x count; wall s)",
                f"{code(p)}; {p['wall']:.1f}",
                f"{code(q)}; {q['wall']:.1f}",
                "429s carry Retry-After",
            ),
        ]
    return rows


def overhead_phase(srv: Serve, scene, methods: list[str], n: int, tree: str = "") -> list[tuple[str, str, str, str]]:
    """Localize p50 / p95 against a cached anchor through the API (a client on loopback: upload, decode,
    localize, answer) and the same call on the library in this process (decode the same JPEG, localize
    against the same prepared reference with the method the API runs), ``n`` calls each, one at a time. The
    library runs with the thread counts (OpenCV, torch, BLAS, OpenMP) that the server's heavy threads set by
    default; the note splits the method's own time into its stages, in the server and in the library."""
    import cv2

    from mapfree import methods as registry
    from mapfree.relocalize import Relocalizer, View
    from mapfree.service.http.heavy import default_method_threads, default_threads, set_method_threads

    set_method_threads(default_method_threads(default_threads()))

    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")
    q_bytes = query.image_path.read_bytes()
    q_form = {k: repr(getattr(query.intrinsics, k)) for k in ("fx", "fy", "cx", "cy")}
    rows = []
    for name in methods:
        m = registry.query_depth_fallback(registry.get(name))  # what the API runs for a query without depth
        loc = Relocalizer.from_method(m)
        prepared = loc.prepare(View(ref.image(), ref.intrinsics, ref.depth("sensor")))
        with srv.client() as c:
            r = c.post(
                "/anchors",
                data={**{k: repr(getattr(ref.intrinsics, k)) for k in ("fx", "fy", "cx", "cy")}, "method": name},
                files={
                    "image": ("r.jpg", ref.image_path.read_bytes(), "image/jpeg"),
                    "depth": ("r.png", ref.depth_path("sensor").read_bytes(), "image/png"),
                },
            )
            if r.status_code != 201:
                rows.append((f"{name}: localize through the API", "-", "-", f"anchor refused: {r.text[:80]}"))
                continue
            url = f"/anchors/{r.json()['id']}/localize"
            api, own, lib, stages = [], [], [], []
            for i in range(n + 3):  # API and library in turns (the same machine load); three to warm up
                t0 = time.perf_counter()
                d = c.post(url, data=q_form, files={"image": ("q.jpg", q_bytes, "image/jpeg")}).json()
                t1 = time.perf_counter()
                if "timings" not in d:
                    raise SystemExit(f"{tree}{name}: localize answered {d}")
                img = cv2.cvtColor(cv2.imdecode(np.frombuffer(q_bytes, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
                est = loc.localize(View(img, query.intrinsics), prepared)
                t2 = time.perf_counter()
                if i >= 3:
                    api.append(t1 - t0)
                    own.append(d["timings"].get("total", 0.0))
                    lib.append(t2 - t1)
                    stages.append((d["timings"], est.timings))
        over = (pct(api, 50) - pct(lib, 50)) / pct(lib, 50) * 100
        inner = (pct(api, 50) - pct(own, 50)) / pct(own, 50) * 100
        split = ", ".join(
            f"{k} {pct([a.get(k, 0.0) for a, _ in stages], 50):.0f} / {pct([b.get(k, 0.0) for _, b in stages], 50):.0f}"
            for k in stages[0][1]
            if k in ("match", "solve", "ransac", "total")
        )
        rows.append(
            (
                f"{tree}{name} ({m.name}): localize p50 / p95, ms",
                f"{pct(lib, 50):.0f} / {pct(lib, 95):.0f}",
                f"{pct(api, 50):.0f} / {pct(api, 95):.0f}",
                f"API - library: {over:+.1f} % of the library's p50; API - the method's own time in the "
                f"server ({pct(own, 50):.0f} ms): {inner:+.1f} %; stages p50 server / library, ms: {split}; ok={est.ok}",
            )
        )
    return rows


def method_names(n: int) -> list[str]:
    """``n`` distinct method names a client may send (offline matchers x solvers x the service's depth
    suffixes), interleaved so that every configuration comes early."""
    from mapfree.methods import OFFLINE_MATCHERS

    combos = [
        (s, d) for d in ("sensor", "mono", "dptkitti", "dptnyu") for s in ("pnp", "procrustes", "emat", "essential")
    ]
    combos += [("emat", "none"), ("essential", "none")]
    names = [f"{m}_{s}_{d}" for s, d in combos for m in OFFLINE_MATCHERS]
    return names[:n]


def pool_phase(srv: Serve, scene, names: list[str]) -> dict:
    """API RSS while each of ``names`` creates an anchor (the method is built, or taken from the pool, and the
    anchor prepared), sampled every 20 ms; the RSS after 10, 50 and all of them."""
    ref = scene.reference
    form = {k: repr(getattr(ref.intrinsics, k)) for k in ("fx", "fy", "cx", "cy")}
    files = {
        "image": ("r.jpg", ref.image_path.read_bytes(), "image/jpeg"),
        "depth": ("r.png", ref.depth_path("sensor").read_bytes(), "image/png"),
    }
    after, codes = {}, []

    def run() -> None:
        with srv.client() as c:
            for i, name in enumerate(names, 1):
                r = c.post("/anchors", data={**form, "method": name}, files=files)
                codes.append(r.status_code)
                if r.status_code == 201:
                    c.delete(f"/anchors/{r.json()['id']}")
                if i in (10, 50, len(names)):
                    after[i] = srv.rss()

    idle, peak, _ = peak_rss(srv.proc.pid, run)
    return {"idle": idle, "peak": peak, "after": after, "codes": codes}


def own_phases(a, phases: set[str]) -> list[tuple[str, str, str, str]]:
    """The phases of this tree alone -> table rows (what, first figure, second figure, note)."""
    tmp, scene = bench_data("bench-service-own-")
    rows = []
    if "overhead" in phases:
        rows.append(("localize against a cached anchor, one at a time", "library", "API", ""))
        trees = [("", ROOT)]
        if a.baseline:  # the same calls against the baseline tree's API first, in the same run
            trees.insert(0, ("baseline: ", Path(a.baseline).resolve()))
        for label, code_root in trees:
            srv = Serve(code_root, tmp, tmp / "data", users=1)
            try:
                rows += overhead_phase(srv, scene, a.overhead_methods.split(","), a.overhead_calls, label)
            finally:
                srv.stop()
    if "pool" in phases:
        names = method_names(a.pool_names)
        runs = [(f"--method-pool-mb {mb}", ROOT, ("--method-pool-mb", mb)) for mb in a.pool_mb.split(",")]
        if a.baseline:  # the same names against the baseline tree (it has no method pool flag)
            runs.insert(0, (f"baseline {a.baseline}", Path(a.baseline).resolve(), ()))
        for label, code_root, extra in runs:
            srv = Serve(code_root, tmp, tmp / "data", users=1, extra=(*extra, "--storage-quota-mb", "0"))
            try:
                r = pool_phase(srv, scene, names)
            finally:
                srv.stop()
            code = ", ".join(f"{c} x {r['codes'].count(c)}" for c in sorted(set(r["codes"])))
            rows.append(
                (
                    f"API RSS, {len(names)} method names, {label} (MB)",
                    f"idle {r['idle']:.0f}",
                    f"peak {r['peak']:.0f}",
                    "after 10 / 50 / all: " + " / ".join(f"{v:.0f}" for v in r["after"].values()) + f"; anchors {code}",
                )
            )
    return rows


def print_before_after(rows, baseline: str) -> None:
    print(f"\nrelocalization API before / after (baseline: {baseline}; {os.cpu_count()} CPUs)")
    w = max(len(r[0]) for r in rows)
    print(f"  {'':<{w}}  {'baseline':>16}  {'now':>16}")
    for name, before, now, note in rows:
        print(f"  {name:<{w}}  {before:>16}  {now:>16}  {note}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--db", default="", help="database URL (default: a fresh SQLite file)")
    ap.add_argument("--submissions", type=int, default=200)
    ap.add_argument("--clients", type=int, default=20)
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--localize-clients", type=int, default=8)
    ap.add_argument("--localize-requests", type=int, default=48)
    ap.add_argument("--upload-rounds", type=int, default=3, help="uploads of the big ZIP per stream (3 streams)")
    ap.add_argument("--health-interval", type=float, default=0.01, help="seconds between /health polls")
    ap.add_argument("--timeout", type=float, default=420.0, help="give up after this many seconds")
    ap.add_argument(
        "--phases",
        default="memory,uploads,submissions,localize",
        help="which phases to run; photo, cache and flood compare with --baseline",
    )
    ap.add_argument("--baseline", default="", help="source tree to compare photo/cache/flood with (a main checkout)")
    ap.add_argument("--side", type=int, default=4096, help="long side of the big photos (photo, cache)")
    ap.add_argument("--anchor-photos", type=int, default=16, help="photos per anchor (cache)")
    ap.add_argument("--flood-calls", type=int, default=45, help="concurrent localize calls (flood)")
    ap.add_argument(
        "--overhead-methods",
        default="best-offline,sift_pnp_sensor",
        help="methods of the overhead phase (API vs library)",
    )
    ap.add_argument("--overhead-calls", type=int, default=30, help="localize calls per method (overhead)")
    ap.add_argument("--pool-names", type=int, default=100, help="distinct method names (pool)")
    ap.add_argument("--pool-mb", default="1024,256", help="--method-pool-mb values to run the pool phase with")
    ap.add_argument(
        "--min-free-mb",
        type=float,
        default=14000,
        help="run the baseline's three-at-once localize only with this much memory available",
    )
    a = ap.parse_args()
    phases = set(a.phases.split(","))
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if phases & OWN:
        rows = own_phases(a, phases & OWN)
        print(f"\nrelocalization API of this tree ({os.cpu_count()} CPUs)")
        w = max(len(r[0]) for r in rows)
        for name, first, second, note in rows:
            print(f"  {name:<{w}}  {first:>14}  {second:>14}  {note}")
        phases -= OWN
        if not phases:
            return 0
    if phases & MINE:
        if not a.baseline:
            raise SystemExit(
                "photo, cache and flood need --baseline DIR (e.g. git worktree add --detach /tmp/mapfree-main main)"
            )
        print_before_after(before_after(a, phases & MINE), a.baseline)
        phases -= MINE
        if not phases:
            return 0
    from sqlalchemy import func, select
    from sqlalchemy.exc import OperationalError

    from mapfree.data import Dataset
    from mapfree.data.synth import SynthOptions, generate
    from mapfree.service.accounts import tokens as auth
    from mapfree.service.database.models import (
        Base,
        Result,
        Submission,
        WorkerRow,
        init_db,
        make_engine,
        session_factory,
    )

    tmp = Path(tempfile.mkdtemp(prefix="bench-service-"))
    generate(
        tmp / "data",
        "val",
        3,
        20,
        seed=3,
        options=SynthOptions(first_scene=460, width=135, height=180, texture_size=128, write_mono=False),
        progress=False,
    )
    db_url = a.db or f"sqlite:///{tmp / 'bench.db'}"
    engine = make_engine(db_url)
    if a.db:
        Base.metadata.drop_all(engine)
    init_db(engine)
    S = session_factory(engine)
    tokens = []
    with S.begin() as db:
        for i in range(a.clients):
            tokens.append(auth.create_user(db, f"client{i}")[1])
    big = big_submission([f"s{460 + i:05d}" for i in range(3)]) if phases & {"uploads", "memory"} else b""
    port = free_port()
    operator = "mf_bench-" + os.urandom(8).hex()  # reads /health/detail (worker count)
    log = open(tmp / "serve.log", "w")  # noqa: SIM115 - the server writes it for as long as it runs
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mapfree",
            "serve",
            "--db",
            db_url,
            "--data",
            str(tmp / "data"),
            "--workers",
            str(a.workers),
            "--port",
            str(port),
            "--lease-seconds",
            "3",
            "--log-level",
            "warning",
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        env={**os.environ, "MAPFREE_OPERATOR_TOKEN": operator},
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.time() + a.timeout
    try:
        while True:
            try:
                detail = httpx.get(url + "/health/detail", timeout=2, headers={"Authorization": f"Bearer {operator}"})
                if len(detail.json()["workers"]) >= a.workers:
                    break
            except (httpx.HTTPError, ValueError, KeyError):
                pass
            if time.time() > deadline or proc.poll() is not None:
                raise SystemExit("server did not start:\n" + (tmp / "serve.log").read_text()[-2000:])
            time.sleep(0.3)

        lock = threading.Lock()
        mem = None
        if "memory" in phases:  # first: the workers' RSS before it is their start-up RSS
            mem = upload_memory(url, proc.pid, tokens, big, S, deadline)
        # ---------------------------------------------------------------- three 38 MB uploads at once
        up = None
        if "uploads" in phases:
            up = upload_pressure(url, proc.pid, tokens, big, a.upload_rounds, a.health_interval)
            big_ids = [r[2] for r in up["uploads"] if r[0] == 202]
            t0 = time.perf_counter()
            wait_evaluated(S, deadline, big_ids, poll=0.5)  # the workers parse them (not the API): wait for it
            up["eval_wall"] = time.perf_counter() - t0
            with S() as db:
                up["statuses"] = [db.get(Submission, i).status for i in big_ids]
        ok = True
        if "submissions" in phases:
            # ---------------------------------------------------------------- 200 submissions, 20 clients
            rng = np.random.default_rng(0)
            payloads = [submission(tmp / "data" / "val", rng) for _ in range(8)]
            upload_lat: list[float] = []
            ids: list[str] = []

            def client(k: int) -> None:
                with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {tokens[k]}"}, timeout=60) as c:
                    for j in range(k, a.submissions, a.clients):
                        t0 = time.perf_counter()
                        r = c.post(
                            "/api/submissions",
                            files={"file": ("s.zip", payloads[j % len(payloads)])},
                            data={"split": "val", "name": f"b{j}", "public": "true"},
                        )
                        dt = time.perf_counter() - t0
                        assert r.status_code == 202, r.text
                        with lock:
                            upload_lat.append(dt)
                            ids.append(r.json()["id"])

            killed: dict = {}

            def killer() -> None:
                """SIGKILL a worker while it evaluates a job."""
                while time.time() < deadline and not killed:
                    try:
                        with S() as db:
                            row = db.execute(
                                select(WorkerRow.pid, Submission.id)
                                .join(Submission, Submission.worker_id == WorkerRow.id)
                                .where(Submission.status == "running")
                            ).first()
                    except OperationalError:  # busy database: look again
                        continue
                    if row is not None:
                        try:
                            os.kill(row[0], signal.SIGKILL)
                            killed.update(pid=row[0], job=row[1])
                        except ProcessLookupError:
                            pass
                        return
                    time.sleep(0.05)

            t_start = time.perf_counter()
            kt = threading.Thread(target=killer)
            with ThreadPoolExecutor(a.clients) as ex:
                futs = [ex.submit(client, k) for k in range(a.clients)]
                time.sleep(0.5)
                kt.start()
                for f in futs:
                    f.result()
            kt.join()
            t_uploaded = time.perf_counter()
            wait_evaluated(S, deadline)
            t_done = time.perf_counter()
            with S() as db:
                mine = Submission.id.in_(ids)  # this phase's submissions only (not the big uploads before)
                statuses = dict(
                    db.execute(select(Submission.status, func.count()).where(mine).group_by(Submission.status)).all()
                )
                n_results = db.scalar(select(func.count()).select_from(Result).where(Result.submission_id.in_(ids)))
                n_distinct = db.scalar(
                    select(func.count(func.distinct(Result.submission_id))).where(Result.submission_id.in_(ids))
                )
                retried = db.scalar(select(func.count()).select_from(Submission).where(mine, Submission.attempts > 1))
                killed_job = db.get(Submission, killed["job"]) if killed else None
            ok = (
                len(ids) == a.submissions
                and statuses.get("done", 0) == a.submissions
                and n_results == n_distinct == a.submissions
            )

        if "localize" in phases:
            # ---------------------------------------------------------------- localize, 8 clients
            scene = Dataset(realmini()).scene("val", "s00000")
            ref = scene.reference
            queries = [q for q in scene.queries][:8]
            form = lambda K: {"fx": str(K.fx), "fy": str(K.fy), "cx": str(K.cx), "cy": str(K.cy)}  # noqa: E731
            with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {tokens[0]}"}, timeout=120) as c:
                anchor = c.post(
                    "/anchors",
                    files={
                        "image": ("r.jpg", ref.image_path.read_bytes()),
                        "depth": ("d.png", ref.depth_path("sensor").read_bytes()),
                    },
                    data={**form(ref.intrinsics), "method": "sift_pnp_sensor"},
                ).json()["id"]
                c.post(
                    f"/anchors/{anchor}/localize",
                    files={"image": ("q.jpg", queries[0].image_path.read_bytes())},
                    data=form(queries[0].intrinsics),
                )  # warm-up: builds the relocalizer, prepares the anchor
            loc_lat: list[float] = []
            loc_ok = [0]

            def loc_client(k: int) -> None:
                with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {tokens[k]}"}, timeout=120) as c:
                    for j in range(k, a.localize_requests, a.localize_clients):
                        q = queries[j % len(queries)]
                        t0 = time.perf_counter()
                        r = c.post(
                            f"/anchors/{anchor}/localize",
                            files={"image": ("q.jpg", q.image_path.read_bytes())},
                            data=form(q.intrinsics),
                        )
                        dt = time.perf_counter() - t0
                        assert r.status_code == 200, r.text
                        with lock:
                            loc_lat.append(dt)
                            loc_ok[0] += bool(r.json()["ok"])

            t0 = time.perf_counter()
            with ThreadPoolExecutor(a.localize_clients) as ex:
                list(ex.map(loc_client, range(a.localize_clients)))
            loc_wall = time.perf_counter() - t0

            # baseline: the same localizations in this process, one at a time, no HTTP
            from mapfree.relocalize import Relocalizer, View

            r = Relocalizer.from_method("sift_pnp_sensor")
            prepared = r.prepare(View(ref.image(), ref.intrinsics, ref.depth("sensor")))
            base_lat = []
            for j in range(min(16, a.localize_requests)):
                q = queries[j % len(queries)]
                t1 = time.perf_counter()
                r.localize(View(q.image(), q.intrinsics), prepared)
                base_lat.append(time.perf_counter() - t1)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
        engine.dispose()

    rows = []
    if mem is not None:
        rows += [
            (
                f"memory: 3 uploads of {len(big) / 1e6:.0f} MB at once, then parsed",
                f"{mem['wall']:.1f} s",
                f"status {sorted(mem['codes'])}; "
                + ", ".join(f"{s} x {mem['statuses'].count(s)}" for s in sorted(set(mem["statuses"]))),
            ),
            ("API process RSS idle / peak (MB)", f"{mem['api_idle']:.0f} / {mem['api_peak']:.0f}", ""),
            (
                f"worker RSS idle / peak, largest of {mem['workers']} (MB)",
                f"{mem['worker_idle']:.0f} / {mem['worker_peak']:.0f}",
                f"peaks {', '.join(f'{x:.0f}' for x in mem['worker_peaks'])}; growth "
                f"{(mem['worker_peak'] - mem['worker_idle']) / (len(big) / 2**20):.2f}x the ZIP",
            ),
        ]
        ok = ok and all(c == 202 for c in mem["codes"]) and set(mem["statuses"]) == {"done"}
    if up is not None:
        h, ih = up["health"], up["idle_health"]
        codes = sorted(c for c, _, _ in up["uploads"])
        times = sorted(t for _, t, _ in up["uploads"])
        rows += [
            (
                f"{len(codes)} uploads of {len(big) / 1e6:.0f} MB, 3 at once (status; time)",
                f"{codes.count(202)} x 202; {times[0]:.1f}-{times[-1]:.1f} s",
                f"{up['window']:.1f} s window",
            ),
            (
                "API RSS idle / max during uploads (MB)",
                f"{up['idle_rss']:.0f} / {up['max_rss']:.0f}",
                "target < 400 MB: " + ("met" if up["max_rss"] < 400 else "MISSED"),
            ),
            (
                "/health p50 / p99 / max during uploads (ms)",
                f"{pct(h, 50):.0f} / {pct(h, 99):.0f} / {pct(h, 100):.0f}",
                f"{len(h)} polls ({up['health_bad']} not 200), idle p50 / p99 {pct(ih, 50):.0f} / {pct(ih, 99):.0f} ms; "
                "target p99 < 100 ms: " + ("met" if pct(h, 99) < 100 and not up["health_bad"] else "MISSED"),
            ),
            (
                f"workers: the {len(up['statuses'])} big submissions evaluated (s)",
                f"{up['eval_wall']:.1f}",
                ", ".join(f"{s} x {up['statuses'].count(s)}" for s in sorted(set(up["statuses"]))),
            ),
        ]
        ok = ok and all(c == 202 for c, _, _ in up["uploads"])
    if "submissions" in phases:
        sub_wall = t_done - t_start
        rows += [
            ("submissions uploaded / evaluated (done)", f"{len(ids)} / {statuses.get('done', 0)}", ""),
            ("result rows (distinct submissions)", f"{n_results} ({n_distinct})", "exactly once" if ok else "MISMATCH"),
            (
                "worker killed mid-job (pid, job attempts)",
                f"{killed.get('pid', '-')}, {killed_job.attempts if killed_job else '-'}",
                f"{retried} job(s) retried",
            ),
            ("upload latency p50 / p99 (ms)", f"{pct(upload_lat, 50):.0f} / {pct(upload_lat, 99):.0f}", ""),
            (
                "evaluation throughput (submissions/s)",
                f"{a.submissions / sub_wall:.1f}",
                f"{sub_wall:.1f} s wall, uploads done at {t_uploaded - t_start:.1f} s",
            ),
        ]
    if "localize" in phases:
        rows += [
            (
                f"localize latency p50 / p99 (ms), {a.localize_clients} clients",
                f"{pct(loc_lat, 50):.0f} / {pct(loc_lat, 99):.0f}",
                f"{loc_ok[0]}/{len(loc_lat)} with a pose",
            ),
            (
                "localize throughput (req/s)",
                f"{len(loc_lat) / loc_wall:.2f}",
                f"{(len(loc_lat) / loc_wall) * np.mean(base_lat):.2f}x in-process serial",
            ),
            (
                "in-process localize p50 (ms), baseline",
                f"{pct(base_lat, 50):.0f}",
                f"HTTP p50 / baseline = {pct(loc_lat, 50) / pct(base_lat, 50):.1f}x",
            ),
        ]
    db_name = db_url.split(":")[0]
    print(f"\nmapfree serve on loopback ({db_name}, {a.workers} workers, {a.clients} clients, {os.cpu_count()} CPUs)")
    w = max(len(r[0]) for r in rows)
    for name, val, note in rows:
        print(f"  {name:<{w}}  {val:>14}  {note}")
    print(
        "PASS: every upload accepted, every submission evaluated exactly once, none lost"
        if ok
        else "FAIL: a refused upload, or lost or duplicated results"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())

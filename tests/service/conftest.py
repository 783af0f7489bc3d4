"""Fixtures of the service tests: a small split with private test ground truth, and a real ``mapfree serve``
(uvicorn + worker processes) on a free loopback port, once per database backend (SQLite, and PostgreSQL when
``MAPFREE_TEST_PG`` holds a URL; ``.ci/services.sh`` starts one); ``make_app``: the app in-process on SQLite."""

from __future__ import annotations

import io
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from mapfree.service import Limits, Settings, create_app

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = ROOT / "test-artifacts"
PG_URL = os.environ.get("MAPFREE_TEST_PG", "")
BACKENDS = [
    "sqlite",
    pytest.param(
        "postgresql",
        marks=pytest.mark.skipif(
            not PG_URL, reason="MAPFREE_TEST_PG is not set (run .ci/services.sh to start PostgreSQL)"
        ),
    ),
]
VAL_SCENES, TEST_SCENES, QUERIES = 2, 2, 20
#: The monitoring token the test servers get (``MAPFREE_OPERATOR_TOKEN``): it reads /health/detail and /metrics.
OPERATOR_TOKEN = "mf_operator-" + uuid.uuid4().hex
OPERATOR = {"Authorization": f"Bearer {OPERATOR_TOKEN}"}


def health_detail(url: str, timeout: float = 2) -> dict:
    """The detailed health (queue, live workers) of the server at ``url``, read with the operator token."""
    return httpx.get(url + "/health/detail", headers=OPERATOR, timeout=timeout).json()


def _realmini() -> Path:
    for c in (ROOT.parent / "shared/data/realmini-dev", Path("/work/shared/data/realmini-dev")):
        if (c / "val").is_dir():
            return c
    pytest.fail("shared/data/realmini-dev not found beside the checkout")


# ------------------------------------------------------------------------------------------- the dataset


def _write_text_split(root: Path, split: str, names: list[str], gt_dir: Path | None, rng) -> None:
    """A split of text files only (what scoring reads): random query poses, per-frame intrinsics."""
    from mapfree.data import write_poses
    from mapfree.geometry import Pose, quat_to_rotmat

    for scene in names:
        d = root / split / scene
        d.mkdir(parents=True)
        frames = ["seq0/frame_00000.jpg"] + [f"seq1/frame_{i:05d}.jpg" for i in range(QUERIES)]
        with open(d / "intrinsics.txt", "w") as f:
            for n in frames:
                f.write(f"{n} 590.5 591.0 269.5 359.5 540 720\n")
        poses = [Pose.identity()]
        for _ in frames[1:]:
            q = rng.normal(size=4) * [0.1, 0.1, 0.1, 0.1] + [1, 0, 0, 0]
            poses.append(Pose(quat_to_rotmat(q / np.linalg.norm(q)), rng.normal(size=3)))
        if gt_dir is None:
            write_poses(d / "poses.txt", frames, poses)
        else:
            (gt_dir / split / scene).mkdir(parents=True)
            write_poses(gt_dir / split / scene / "poses.txt", frames, poses)
            (d / "poses.txt").write_text("".join(f"{n} 0 0 0 0 0 0 0\n" for n in frames))


@dataclass
class Split:
    root: Path
    gt: Path


@pytest.fixture(scope="session")
def split_data(tmp_path_factory) -> Split:
    """val (public ground truth) and test (public zeros, private ground truth), a few scenes each."""
    base = tmp_path_factory.mktemp("mapfree-data")
    root, gt = base / "data", base / "private-gt"
    try:
        from mapfree.data.synth import generate
    except ImportError:
        generate = None
    if generate is not None:
        from mapfree.data.synth import SynthOptions

        small = dict(width=135, height=180, texture_size=128, write_mono=False)
        generate(
            root, "val", VAL_SCENES, QUERIES, seed=1, options=SynthOptions(first_scene=460, **small), progress=False
        )
        generate(
            root,
            "test",
            TEST_SCENES,
            QUERIES,
            seed=2,
            private_gt_dir=gt,
            options=SynthOptions(first_scene=525, **small),
            progress=False,
        )
    else:
        rng = np.random.default_rng(0)
        _write_text_split(root, "val", [f"s{460 + i:05d}" for i in range(VAL_SCENES)], None, rng)
        _write_text_split(root, "test", [f"s{525 + i:05d}" for i in range(TEST_SCENES)], gt, rng)
    return Split(root, gt)


def truth_poses(scene_dir: Path) -> list[tuple[str, list[float]]]:
    rows = []
    for line in (scene_dir / "poses.txt").read_text().splitlines():
        p = line.split()
        if len(p) == 8 and "#" not in p[0] and p[0].startswith("seq1/"):
            rows.append((p[0], [float(x) for x in p[1:]]))
    return rows


def make_submission(split_root: Path, noise: float = 0.0, seed: int = 0, drop_every: int = 0) -> bytes:
    """A submission ZIP built from ground-truth poses (``split_root``: a folder of sNNNNN/ scenes), with
    optional translation noise (metres) and dropped frames; confidences vary so that AUC is exercised."""
    rng = np.random.default_rng(seed)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for scene in sorted(p for p in split_root.iterdir() if p.is_dir()):
            lines = []
            for i, (name, v) in enumerate(truth_poses(scene)):
                if drop_every and i % drop_every == 1:
                    continue
                t = np.array(v[4:]) + rng.normal(scale=noise, size=3) if noise else np.array(v[4:])
                conf = float(rng.uniform(1, 100))
                lines.append(
                    f"{name} {' '.join(f'{x:.9f}' for x in v[:4])} {' '.join(f'{x:.9f}' for x in t)} {conf:.3f}"
                )
            z.writestr(f"pose_{scene.name}.txt", "\n".join(lines) + "\n")
    return buf.getvalue()


def pose_text(scene_dir: Path, lines: int, seed: int) -> bytes:
    """``lines`` pose lines over the scene's query frames (repeats are duplicates, which the reader skips)."""
    names = [n for n, _ in truth_poses(scene_dir)]
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(lines, 8))
    v[:, 7] = np.abs(v[:, 7])
    return "".join(
        f"{names[i % len(names)]} {r[0]:.9f} {r[1]:.9f} {r[2]:.9f} {r[3]:.9f} {r[4]:.9f} {r[5]:.9f} "
        f"{r[6]:.9f} {r[7]:.6f}\n"
        for i, r in enumerate(v)
    ).encode()


def zip_of(entries: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    """A ZIP holding exactly ``entries`` (name -> bytes)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return buf.getvalue()


def png_of(h: int, w: int, channels: int = 3, dtype=np.uint8) -> bytes:
    """A blank PNG of that size, channel count and bit depth; a single-channel 16-bit one is a depth map of 1 m
    everywhere (an all-zero map is refused as an anchor's depth)."""
    import cv2

    fill = 1000 if channels == 1 and dtype == np.uint16 else 0
    ok, buf = cv2.imencode(".png", np.full((h, w, channels) if channels > 1 else (h, w), fill, dtype))
    assert ok
    return buf.tobytes()


# ---------------------------------------------------------------------------------------------- servers


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def mapfree(command: str, *args: str, env=None) -> str:
    """Run ``mapfree COMMAND ...`` as ``python -m mapfree.cli.COMMAND`` (same code, without importing the other
    subcommands and their heavy dependencies)."""
    out = subprocess.run(
        [sys.executable, "-m", f"mapfree.cli.{command}", *args], capture_output=True, text=True, timeout=120, env=env
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


_PG_CREATED: list[str] = []


def fresh_postgres(tag: str) -> str:
    """A new empty database next to MAPFREE_TEST_PG's (needs CREATEDB, which .ci/services.sh grants); without
    that privilege, the given database itself with its tables dropped."""
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    from mapfree.service.database.models import Base, make_engine, normalize_url

    base = make_url(normalize_url(PG_URL))
    name = f"mapfree_t_{tag}_{uuid.uuid4().hex[:8]}"
    admin = create_engine(base, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            c.execute(text(f'CREATE DATABASE "{name}"'))
        _PG_CREATED.append(name)
        return base.set(database=name).render_as_string(hide_password=False)
    except Exception:
        engine = make_engine(PG_URL)
        Base.metadata.drop_all(engine)
        with engine.begin() as c:  # and the schema version with the tables
            c.execute(text("DROP TABLE IF EXISTS alembic_version"))
        engine.dispose()
        return PG_URL
    finally:
        admin.dispose()


def drop_postgres_databases() -> None:
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    from mapfree.service.database.models import normalize_url

    if not _PG_CREATED:
        return
    admin = create_engine(make_url(normalize_url(PG_URL)), isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        for name in _PG_CREATED:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    admin.dispose()
    _PG_CREATED.clear()


@dataclass
class Server:
    url: str
    db_url: str
    backend: str
    data: Split
    log_path: Path
    proc: subprocess.Popen
    tokens: dict[str, str] = field(default_factory=dict)

    def client(self, user: str | None = None, **kw) -> httpx.Client:
        headers = {"Authorization": f"Bearer {self.tokens[user]}"} if user else {}
        headers.update(kw.pop("headers", {}))
        return httpx.Client(base_url=self.url, headers=headers, timeout=60, **kw)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_done(self, sid: str, user: str, timeout: float = 60) -> dict:
        with self.client(user) as c:
            deadline = time.time() + timeout
            while time.time() < deadline:
                d = c.get(f"/api/submissions/{sid}").json()
                if d["status"] in ("done", "failed"):
                    return d
                time.sleep(0.2)
        raise AssertionError(f"submission {sid} not finished after {timeout} s:\n{self.log()[-3000:]}")


def create_users(db_url: str, users: dict[str, int | None], admin: bool = False) -> dict[str, str]:
    """Accounts made in-process (what `mapfree admin create-user [--admin]` does): name -> token."""
    from mapfree.service.accounts import tokens as auth
    from mapfree.service.database.models import init_db, make_engine, session_factory

    engine = make_engine(db_url)
    init_db(engine)
    out = {}
    with session_factory(engine).begin() as db:
        for name, limit in users.items():
            user, out[name] = auth.create_user(db, name, admin=admin)
            user.test_daily_limit = limit
    engine.dispose()
    return out


def start_server(
    db_url: str,
    backend: str,
    data: Split,
    workdir: Path,
    workers: int = 2,
    extra: tuple[str, ...] = (),
    port: int | None = None,
    tokens: dict[str, str] | None = None,
) -> Server:
    """A ``mapfree serve`` on ``db_url``, healthy with ``workers`` workers; ``tokens``: the accounts of a database
    another server made already (else alice, made with ``mapfree admin``, bob, and carol with a daily
    test limit of 2 are created)."""
    port = port or free_port()
    log_path = workdir / f"serve-{backend}-{port}.log"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MAPFREE_DB": db_url, "MAPFREE_OPERATOR_TOKEN": OPERATOR_TOKEN}
    if tokens is None:
        tokens = {"alice": mapfree("admin", "--db", db_url, "create-user", "alice", env=env).splitlines()[-1]}
        tokens.update(create_users(db_url, {"bob": None, "carol": 2}))
    # `python -m mapfree.cli.serve` is `mapfree serve` without importing every other subcommand (faster start)
    cmd = [
        sys.executable,
        "-m",
        "mapfree.cli.serve",
        "--db",
        db_url,
        "--data",
        str(data.root),
        "--gt",
        str(data.gt),
        "--workers",
        str(workers),
        "--port",
        str(port),
        "--lease-seconds",
        "5",
        "--max-upload-mb",
        "2",
        *extra,
    ]
    logf = open(log_path, "w")  # noqa: SIM115 - the server writes it for as long as it runs
    proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    deadline = time.time() + 90
    while time.time() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited:\n{log_path.read_text()[-3000:]}")
        try:
            h = health_detail(url)
            if len(h.get("workers", [])) >= workers:
                break
        except (httpx.HTTPError, ValueError):
            pass
        time.sleep(0.3)
    else:
        stop_server(proc)
        raise RuntimeError(f"server did not become healthy:\n{log_path.read_text()[-3000:]}")
    return Server(url, db_url, backend, data, log_path, proc, tokens)


def stop_server(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def db_url_for(backend: str, tmp: Path) -> str:
    if backend == "sqlite":
        return f"sqlite:///{tmp / ('svc-' + uuid.uuid4().hex[:6] + '.db')}"
    return fresh_postgres("svc")


@pytest.fixture(scope="session")
def servers(split_data, tmp_path_factory):
    """Started on first use, one per backend, stopped at the end of the session."""
    running: dict[str, Server] = {}

    def get(backend: str) -> Server:
        if backend not in running:
            tmp = tmp_path_factory.mktemp(f"server-{backend}")
            running[backend] = start_server(db_url_for(backend, tmp), backend, split_data, tmp)
        return running[backend]

    yield get
    problems = []
    stoppers = [threading.Thread(target=stop_server, args=(srv.proc,)) for srv in running.values()]
    for t in stoppers:
        t.start()
    for t in stoppers:
        t.join()
    for backend, srv in running.items():
        log = srv.log()
        ARTIFACTS.mkdir(exist_ok=True)
        shutil.copy(srv.log_path, ARTIFACTS / f"serve-{backend}.log")
        if "unhandled error" in log:
            problems.append(f"{backend}: the server answered a 500 (see test-artifacts/serve-{backend}.log)")
        if any(token in log for token in srv.tokens.values()):
            problems.append(f"{backend}: an API token appeared in the logs")
    drop_postgres_databases()
    assert not problems, problems


@pytest.fixture(scope="session", params=BACKENDS)
def server(request, servers) -> Server:
    """A running ``mapfree serve`` (2 workers) per backend, shared by the tests of that backend."""
    return servers(request.param)


@pytest.fixture(scope="session")
def sqlite_server(servers) -> Server:
    """The SQLite server, for the browser tests."""
    return servers("sqlite")


@pytest.fixture(scope="session")
def realmini_dir() -> Path:
    return _realmini()


@pytest.fixture(scope="session", autouse=True)
def _drop_test_databases():
    yield
    drop_postgres_databases()


@dataclass
class App:
    client: TestClient
    settings: Settings
    tokens: dict[str, str]

    def auth(self, user: str) -> dict:
        return {"Authorization": f"Bearer {self.tokens[user]}"}


@pytest.fixture
def make_app(split_data, tmp_path):
    """``make_app(**settings)``: the real FastAPI app on a fresh SQLite file, called in-process."""
    clients = []

    def make(limits: Limits | None = None, **kw) -> App:
        url = f"sqlite:///{tmp_path / f'app{len(clients)}.db'}"
        kw.setdefault("operator_token", OPERATOR_TOKEN)
        settings = Settings(
            db_url=url, data_root=split_data.root, gt_root=split_data.gt, limits=limits or Limits(), **kw
        )
        tokens = create_users(url, {"ann": None, "ben": None})
        client = TestClient(create_app(settings), raise_server_exceptions=False)
        clients.append(client)
        return App(client, settings, tokens)

    yield make
    for c in clients:
        c.close()

"""`make test`'s split over pytest-xdist workers (tests/conftest.py): a test file's tests stay on one worker, all of
tests/service/ shares one, and so do the files that start Ray clusters; the work still spreads over both workers."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("xdist")

RECORD = """
import json, os, pathlib

def _record(name):
    with open({log!r}, "a") as f:
        f.write(json.dumps([{file!r}, name, os.environ["PYTEST_XDIST_WORKER"]]) + "\\n")
""" + "".join(f"\n\ndef test_{i}():\n    _record('{i}')\n" for i in range(6))


def test_files_service_and_ray_keep_to_one_worker_each(tmp_path):
    tests = tmp_path / "tests"
    (tests / "service").mkdir(parents=True)
    shutil.copy(Path(__file__).with_name("conftest.py"), tests / "conftest.py")
    log = tmp_path / "workers.jsonl"
    files = ["test_a.py", "test_b.py", "test_c.py", "test_build.py", "test_run_ray.py"]
    files += ["service/test_x.py", "service/test_y.py"]
    for f in files:
        (tests / f).write_text(RECORD.format(log=str(log), file=f))
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "2", "-q", "-p", "no:cacheprovider", "tests"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert len(rows) == 6 * len(files)
    worker = {}
    for f, _, w in rows:
        worker.setdefault(f, set()).add(w)
    assert all(len(ws) == 1 for ws in worker.values()), worker  # a file on one worker
    assert worker["service/test_x.py"] == worker["service/test_y.py"]
    assert worker["test_build.py"] == worker["test_run_ray.py"]
    assert len(set().union(*worker.values())) == 2  # both workers had work

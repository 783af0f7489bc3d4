"""ARCHITECTURE.md's one-file examples run as written: the matcher, depth source and solver put together relocalize
a real photo pair, and the service resource answers through the real app."""

from __future__ import annotations

import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from mapfree.data import Dataset
from mapfree.geometry import rotation_angle_deg

DOC = Path(__file__).resolve().parents[1] / "ARCHITECTURE.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)


def _module(path: str, monkeypatch) -> types.ModuleType:
    """The example whose first line names ``path``, executed as a module of that name."""
    (code,) = [b for b in _blocks() if b.startswith(f"# {path}\n")]
    name = "architecture_example_" + Path(path).stem
    mod = types.ModuleType(name)
    monkeypatch.setitem(sys.modules, name, mod)  # dataclasses and pydantic resolve annotations through it
    exec(compile(code, f"ARCHITECTURE.md:{path}", "exec"), mod.__dict__)
    return mod


def test_every_python_example_is_checked_here():
    files = [b.splitlines()[0] for b in _blocks()]
    assert files == [
        "# src/mapfree/matching/orb.py",
        "# src/mapfree/depth/npy.py",
        "# src/mapfree/solvers/opencv_pnp.py",
        "from mapfree.relocalize import Relocalizer",
        "# src/mapfree/service/splits/router.py",
    ]


def test_matcher_depth_and_solver_examples_relocalize_a_real_pair(realmini, tmp_path, monkeypatch):
    import shutil

    orb = _module("src/mapfree/matching/orb.py", monkeypatch)
    npy = _module("src/mapfree/depth/npy.py", monkeypatch)
    pnp = _module("src/mapfree/solvers/opencv_pnp.py", monkeypatch)
    root = tmp_path / "data"
    shutil.copytree(realmini, root)
    scene = Dataset(root).scene("val", "s00000")
    for frame in (scene.reference, scene.frame("seq1/frame_00009.jpg")):  # the sensor maps as float .npy files
        np.save(frame.image_path.with_suffix(".sensor.npy"), frame.depth("sensor"))

    (together,) = [b for b in _blocks() if b.startswith("from mapfree.relocalize import Relocalizer")]
    ns = {"ORBMatcher": orb.ORBMatcher, "NpyDepth": npy.NpyDepth, "OpenCVPnPSolver": pnp.OpenCVPnPSolver}
    exec(together, {**ns, "scene": scene}, ns)
    est = ns["estimate"]

    query = scene.frame("seq1/frame_00009.jpg")
    gt = query.pose @ scene.reference.pose.inverse()
    assert est.pose is not None, est.reason
    assert est.inliers >= 20
    assert np.linalg.norm(est.pose.center - gt.center) < 0.1
    assert rotation_angle_deg(est.pose.R, gt.R) < 2.0

    # The parts behave as their interfaces promise: no depth file -> None; too few matches -> a failure record.
    assert npy.NpyDepth("nosuch").depth(query) is None
    few = orb.ORBMatcher(max_features=3)
    solved = pnp.OpenCVPnPSolver().solve(
        few.match(few.extract(scene.reference.image()), few.extract(query.image())),
        scene.reference.intrinsics,
        query.intrinsics,
        scene.reference.depth("sensor"),
    )
    assert solved.pose is None and "6 needed" in solved.reason


def test_service_resource_example_answers_through_the_app(realmini, tmp_path, monkeypatch):
    pytest.importorskip("fastapi")
    from fastapi.testclient import TestClient

    from mapfree.service import Settings, create_app

    splits = _module("src/mapfree/service/splits/router.py", monkeypatch)
    settings = Settings(db_url=f"sqlite:///{tmp_path / 'app.db'}", data_root=realmini, gt_root=tmp_path / "gt")
    app = create_app(settings)
    app.include_router(splits.router)
    with TestClient(app) as client:
        r = client.get("/api/splits")
    assert r.status_code == 200, r.text
    assert r.json() == [{"name": "val", "scenes": len(Dataset(realmini).scene_names("val"))}]
    assert len(Dataset(realmini).scene_names("val")) == 4

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
        "# src/mapfree/matching/__init__.py, in _REGISTRY",
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


def test_matcher_example_needs_its_file_and_its_registry_line_and_nothing_else(realmini, tmp_path, monkeypatch, capsys):
    """Written where ARCHITECTURE.md puts it and registered by its one line, the ORB matcher is created by name,
    listed by ``available()``, ``mapfree match --help`` and the API table, and matches two real photos from the CLI."""
    from mapfree import matching
    from mapfree.cli import main
    from mapfree.options import OptionError

    (code,) = [b for b in _blocks() if b.startswith("# src/mapfree/matching/orb.py\n")]
    (line,) = [b for b in _blocks() if b.startswith("# src/mapfree/matching/__init__.py, in _REGISTRY\n")]
    folder = tmp_path / "matching"
    folder.mkdir()
    (folder / "orb.py").write_text(code)
    monkeypatch.setattr(matching, "__path__", [*matching.__path__, str(folder)])  # as if it were in the package
    monkeypatch.setattr(matching, "_REGISTRY", {**matching._REGISTRY, **eval("{" + line + "}", vars(matching))})
    try:
        assert matching.names()[-1] == "orb" and "orb" in matching.available()
        assert "| ORB (OpenCV) | `orb` | `ORBMatcher` |" in matching.table()
        assert matching.create("ORB", max_features=500).options.max_features == 500
        with pytest.raises(OptionError, match="max_feature"):
            matching.check_options("orb", {"max_feature": 500})
        with pytest.raises(SystemExit):
            main(["match", "--help"])
        assert ",orb;" in "".join(capsys.readouterr().out.split())  # argparse wraps the list of names
        img0, img1 = (realmini / "val/s00000" / f for f in ("seq0/frame_00000.jpg", "seq1/frame_00009.jpg"))
        out = tmp_path / "orb.npz"
        assert (
            main(["match", str(img0), str(img1), "--matcher", "orb", "--option", "max_features=2000", "-o", str(out)])
            == 0
        )
        saved = np.load(out)
        assert str(saved["matcher"]) == "orb" and len(saved["kpts0"]) >= 100
        assert "orb" in capsys.readouterr().out
    finally:
        sys.modules.pop("mapfree.matching.orb", None)


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

"""``mapfree`` start-up imports only what the chosen subcommand needs: scoring never loads torch, OpenCV, SciPy's
rotations or the method registry (each costs a fraction of a second, paid on every ``mapfree evaluate``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mapfree.benchmark import write_submission
from mapfree.data import read_poses

HEAVY = ("torch", "cv2", "scipy.spatial", "mapfree.methods", "mapfree.relocalize", "mapfree.service", "matplotlib")

# Runs the command as the console script does, then prints which heavy modules ended up loaded.
PROBE = """
import json, sys
from mapfree.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as e:  # --help exits through argparse
    code = e.code
print(json.dumps({"code": code, "loaded": sorted(m for m in HEAVY if m in sys.modules)}), file=sys.stderr)
""".replace("HEAVY", repr(HEAVY))


def _probe(*argv: str) -> tuple[dict, str]:
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    p = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, env=env, timeout=120)
    return json.loads(p.stderr.strip().splitlines()[-1]), p.stdout


def _perfect_submission(root: Path, path: Path) -> None:
    est = {}
    for d in sorted((root / "val").iterdir()):
        table = read_poses(d / "poses.txt")
        est[d.name] = [(n, table.pose(i), 1.0) for i, n in enumerate(table.names) if n.startswith("seq1/")]
    write_submission(path, est)


@pytest.mark.parametrize("argv", [("evaluate", "--help"), ("--help",), ("relocalize", "--help")])
def test_help_loads_no_heavy_module(argv):
    result, out = _probe(*argv)
    assert result == {"code": 0, "loaded": []}, result
    assert "usage: mapfree" in out


def test_evaluate_scores_without_heavy_modules(realmini, tmp_path):
    sub = tmp_path / "sub.zip"
    _perfect_submission(realmini, sub)
    result, out = _probe("evaluate", str(sub), "--dataset", str(realmini), "--json")
    assert result == {"code": 0, "loaded": []}, result
    metrics = json.loads(out)["metrics"]
    assert metrics["Estimates for % of frames"] == 1.0 and metrics["Precision @ VCRE < 90px"] == 1.0
    result, out = _probe("evaluate", str(sub), "--dataset", str(realmini), "--per-scene", "--compat", "official")
    assert result == {"code": 0, "loaded": []}, result
    assert "s00003" in out

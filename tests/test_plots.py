"""Evaluation figures: written as PNG and PDF, also for a submission without any estimate."""

from __future__ import annotations

import numpy as np

from mapfree.benchmark import evaluate, save_plots, write_submission
from mapfree.benchmark.plots import precision_ratio_figure
from mapfree.cli import main as cli_main
from mapfree.data import read_poses
from mapfree.geometry import Pose


def _estimates(root, shift: float) -> dict:
    out = {}
    for d in sorted((root / "val").iterdir()):
        table = read_poses(d / "poses.txt")
        rows = []
        for i, n in enumerate(table.names):
            if n.startswith("seq1/"):
                p = table.pose(i)
                rows.append((n, Pose(p.R, p.t + np.array([shift * (i % 3), 0, 0])), float(i % 4)))
        out[d.name] = rows
    return out


def test_save_plots(realmini, tmp_path):
    report = evaluate(_estimates(realmini, 0.2), realmini, "val")
    paths = save_plots(report, tmp_path / "plots", formats=("png",))
    assert sorted(p.name for p in paths) == ["precision_ratio.png", "scenes.png", "vcre_cdf.png"]
    assert all(p.read_bytes()[:8].startswith(b"\x89PNG") for p in paths)
    # The precision curve ends at the headline precision (all frames kept).
    fig = precision_ratio_figure(report)
    line = fig.axes[0].lines[0]
    assert line.get_ydata()[-1] == report.metrics["Precision @ VCRE < 90px"]


def test_cli_plots_without_estimates(realmini, tmp_path):
    write_submission(tmp_path / "empty.zip", {})
    rc = cli_main(["evaluate", str(tmp_path / "empty.zip"), "--dataset", str(realmini), "--plots", str(tmp_path / "p")])
    assert rc == 0
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == sorted(
        f"{n}.{e}" for n in ("precision_ratio", "vcre_cdf", "scenes") for e in ("png", "pdf")
    )
    assert (tmp_path / "p" / "scenes.pdf").read_bytes().startswith(b"%PDF")

"""The per-place picture: where the cameras are, how the scans overlap, how well the scale fits."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..data.io import read_poses

__all__ = ["plot_report"]


def plot_report(scene: Path, report: dict, out: Path) -> None:
    """``out`` PNG: top view of the metric camera centres per scan, the overlap histogram, the numbers."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1, ax2) = plt.subplots(1, 3, figsize=(13, 4))
    table = read_poses(scene / "poses.txt")
    if np.linalg.norm(table.q, axis=1).all():  # test scenes hide their poses
        centres = np.stack([p.center for i in range(len(table)) if (p := table.pose(i)) is not None])
        seqs = np.array([n.split("/")[0] for n in table.names])
        for s in sorted(set(seqs)):
            c = centres[seqs == s]
            ax0.plot(c[:, 0], c[:, 2], ".-", label=s, ms=4)
        ax0.plot([0], [0], "k*", ms=10, label="origin (reference)")
        ax0.set_aspect("equal", adjustable="datalim")
        ax0.legend(fontsize=8)
    ax0.set(title="camera centres, top view (m)", xlabel="x", ylabel="z")
    h = report.get("overlap_histogram", {})
    if h:
        edges = np.array(h["bins"])
        mid, w = (edges[:-1] + edges[1:]) / 2, np.diff(edges) * 0.4
        ax1.bar(mid - w / 2, h["within"], w, label="within a scan")
        ax1.bar(mid + w / 2, h["across"], w, label="across scans")
        ax1.legend(fontsize=8)
    ax1.set(title="overlap of frame pairs", xlabel="overlap", ylabel="pairs")
    scale = report.get("scale", {})
    lines = [
        f"place {Path(report['place']).name} -> {report['scene']} ({report['split']})",
        f"registered {report.get('registered')}/{report.get('images')} images",
    ]
    lines += [f"  {k}: {v['registered']}/{v['images']}" for k, v in report.get("scans", {}).items()]
    rep = report.get("reprojection_error_px")
    lines += [
        f"3D points {report.get('points3D')}, reprojection {rep:.2f} px" if rep is not None else "",
        f"scale {scale.get('scale', float('nan')):.4g} from {scale.get('source')}",
        f"scale residual {100 * (scale.get('residual') or 0):.2f} %",
        f"{report.get('seconds', 0):.1f} s",
    ]
    ax2.axis("off")
    ax2.text(0, 1, "\n".join(lines), va="top", family="monospace", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)

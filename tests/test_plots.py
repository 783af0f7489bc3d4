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
    assert rc == 3  # scored and plotted, but nothing was estimated
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == sorted(
        f"{n}.{e}" for n in ("precision_ratio", "vcre_cdf", "scenes") for e in ("png", "pdf")
    )
    assert (tmp_path / "p" / "scenes.pdf").read_bytes().startswith(b"%PDF")


def _labels(axis) -> list[str]:
    """The tick labels drawn inside the axis' view."""
    lo, hi = axis.get_view_interval()
    ticks = axis.get_ticklabels(minor=False) + axis.get_ticklabels(minor=True)
    return [t.get_text() for t in ticks if t.get_text() and lo <= t.get_position()[axis is axis.axes.yaxis] <= hi]


def test_scene_scatter_labels_narrow_ranges(realmini):
    """Per-scene medians within less than a decade (0.22-0.4 m, 6-17°, as a real SIFT run on realmini-dev gives)
    still get numbers on both log axes: the scatter once showed a translation axis without a single label."""
    from scipy.spatial.transform import Rotation

    from mapfree.benchmark.plots import scene_scatter_figure

    est = {}
    for k, (scene, rows) in enumerate(sorted(_estimates(realmini, 0.0).items())):
        R = Rotation.from_euler("y", 6.0 + 3.5 * k, degrees=True).as_matrix()
        est[scene] = [(n, Pose(R @ p.R, R @ p.t + np.array([0.22 + 0.06 * k, 0, 0])), c) for n, p, c in rows]
    fig = scene_scatter_figure(evaluate(est, realmini, "val"))
    fig.canvas.draw()
    ax = fig.axes[0]
    assert len(_labels(ax.yaxis)) >= 2, _labels(ax.yaxis)
    assert len(_labels(ax.xaxis)) >= 2, _labels(ax.xaxis)
    assert all("e" not in s for s in _labels(ax.yaxis) + _labels(ax.xaxis))  # plain numbers, no 2e-01


def test_unwritable_output_is_a_clean_error(realmini, tmp_path, capsys):
    """--plots / --viz into a place that cannot be written (here below a regular file; also a read-only or full
    disk): one line naming the path and exit 1, no traceback."""
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("")
    write_submission(tmp_path / "empty.zip", {})
    assert (
        cli_main(
            ["evaluate", str(tmp_path / "empty.zip"), "--dataset", str(realmini), "--plots", str(blocker / "plots")]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert err.startswith("mapfree evaluate: error:") and str(blocker / "plots") in err and "Traceback" not in err
    scene = realmini / "val" / "s00000"
    assert (
        cli_main(
            [
                "relocalize",
                str(scene / "seq0/frame_00000.jpg"),
                str(scene / "seq1/frame_00010.jpg"),
                "--method",
                "sift_pnp_sensor",
                "--viz",
                str(blocker / "viz.png"),
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert err.startswith("mapfree relocalize: error:") and str(blocker) in err


def _visible_labels(axis, renderer):
    lo, hi = axis.get_view_interval()
    return [
        t
        for t in axis.get_ticklabels(minor=False) + axis.get_ticklabels(minor=True)
        if t.get_text() and lo <= t.get_position()[axis is axis.axes.yaxis] <= hi
    ]


def test_scene_scatter_tick_labels_never_overlap_and_empty_scenes_are_named(realmini):
    """Per-scene medians over 2-3 decades once labelled 0.3 and 0.4 (300, 400) on top of each other; a scene
    without any estimate vanished from the figure without a word."""
    import copy

    import numpy as np

    from mapfree.benchmark import Scores, evaluate
    from mapfree.benchmark.plots import scene_scatter_figure
    from mapfree.geometry import Pose

    gt = {}
    for d in sorted((realmini / "val").iterdir())[:3]:
        from mapfree.data import read_poses

        t = read_poses(d / "poses.txt")
        gt[d.name] = [
            (n, Pose(t.pose(i).R, t.pose(i).t + 0.3), 1.0) for i, n in enumerate(t.names) if n.startswith("seq1/")
        ]
    base = evaluate(gt, realmini, "val")
    rng = np.random.default_rng(0)
    for _trial in range(12):
        report = copy.copy(base)
        lo_r, lo_t = 10 ** rng.uniform(-1.5, 1), 10 ** rng.uniform(-2, 0)
        report.per_scene = {
            f"s{i:05d}": Scores.from_dict(
                {
                    "Average Median Rotation Error": lo_r * 10 ** rng.uniform(0, 2.6),
                    "Average Median Translation Error": lo_t * 10 ** rng.uniform(0, 2.6),
                    "Precision @ VCRE < 90px": 0.5,
                }
            )
            for i in range(16)
        }
        fig = scene_scatter_figure(report)
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        for axis in (fig.axes[0].xaxis, fig.axes[0].yaxis):
            labels = _visible_labels(axis, renderer)
            boxes = [t.get_window_extent(renderer) for t in labels]
            clash = [
                (a.get_text(), b.get_text())
                for i, a in enumerate(labels)
                for j, b in enumerate(labels)
                if i < j and boxes[i].overlaps(boxes[j])
            ]
            assert len(labels) >= 2 and not clash, clash
    fig = scene_scatter_figure(base)  # realmini has 4 val scenes: the 4th got no estimate
    missing = sorted(set(base.per_scene) - set(gt))
    assert missing
    texts = [t.get_text() for t in fig.axes[0].texts] + [fig.axes[0].get_title()]
    assert any(all(s in t for s in missing) for t in texts), texts
    assert f"3 of {len(base.per_scene)} scenes" in fig.axes[0].get_title()

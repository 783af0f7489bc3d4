"""One self-contained HTML page of an evaluation: headline and per-scene tables, the three evaluation figures and
the worst frames, every picture embedded (base64: the plots as PNG, the frames as JPEG), so the file can be mailed
or archived on its own (about 1.5 MB with eight worst frames of the dataset's images).

The worst frames' pictures come from a caller-supplied ``figure(scene, frame)`` (JPEG or PNG bytes, or None): the
CLI looks for the figure a ``mapfree run --viz DIR`` drew, else draws the AR check from the dataset's images.
"""

from __future__ import annotations

import base64
import html
import io
import math
import os
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..data.io import naming
from .report import NOT_PROBABILITIES, Report, _fmt, format_calibration

__all__ = ["write_html", "frame_figure_path", "worst_frames"]

FigureSource = Callable[[str, str], "bytes | None"]

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:2em auto;max-width:1100px;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.5em 0}td,th{padding:.25em .7em;border-bottom:1px solid #eee;text-align:right}
th{background:#f5f5f5}td:first-child,th:first-child{text-align:left}.plots img{width:32%;min-width:300px}
.frame{margin:1em 0}.frame img{max-width:100%;border:1px solid #ccc}.problem{color:#a40}.muted{color:#777}
"""


def frame_figure_path(viz_dir: os.PathLike | str, scene: str, frame: str, suffix: str = ".jpg") -> Path:
    """``VIZ/s00000/seq1_frame_00005.jpg``: where ``mapfree run --viz VIZ`` draws a frame's figure (``.png``: where
    runs before JPEG figures drew it)."""
    return Path(viz_dir) / scene / (frame.replace("/", "_").rsplit(".", 1)[0] + suffix)


def worst_frames(report: Report, n: int = 8) -> list[int]:
    """Indices of the ``n`` estimated frames with the largest VCRE (the metric the leaderboard ranks by)."""
    idx = np.flatnonzero(report.estimated)
    return idx[np.argsort(-report.vcre[idx], kind="stable")][:n].tolist()


def _img(data: bytes, alt: str) -> str:
    mime = "image/jpeg" if data[:3] == b"\xff\xd8\xff" else "image/png"
    return f'<img alt="{html.escape(alt)}" src="data:{mime};base64,{base64.b64encode(data).decode()}">'


def _fig_png(fig) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def _table(header: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _num(v: float, fmt: str) -> str:
    return format(v, fmt) if v is not None and math.isfinite(v) else "—"


def _worst_section(report: Report, worst: int, figure: FigureSource | None, source_note: str) -> list[str]:
    """The page's section of the ``worst`` estimated frames (largest VCRE), each with its figure when given."""
    idx = worst_frames(report, worst)
    if not idx:
        return []
    parts = [f"<h2>Worst {len(idx)} estimated frames (largest VCRE)</h2>"]
    if source_note:
        parts.append(f"<p class='muted'>{html.escape(source_note)}</p>")
    for i in idx:
        scene, frame = str(report.scene[i]), str(report.frame[i])
        head = (
            f"{scene} {frame}: VCRE {_num(report.vcre[i], '.0f')} px, "
            f"{_num(report.trans_err[i], '.2f')} m, {_num(report.rot_err[i], '.1f')}°, "
            f"confidence {_num(report.confidence[i], '.3g')}"
        )
        png = figure(scene, frame) if figure is not None else None
        parts.append(
            f"<div class='frame'><b>{html.escape(head)}</b><br>"
            + (_img(png, f"{scene} {frame}") if png else "<span class='muted'>no figure</span>")
            + "</div>"
        )
    return parts


def write_html(
    report: Report,
    path: os.PathLike | str,
    *,
    title: str = "Map-free evaluation",
    figure: FigureSource | None = None,
    worst: int = 8,
    source_note: str = "",
) -> Path:
    """Write the report page at ``path`` (parent folders created) and return it."""
    from .plots import figures_of

    n = len(report.estimated)
    parts = [
        f"<h1>{html.escape(title)}</h1>",
        f"<p>{html.escape(report.split)} split, {report.track}-frame track, {len(report.per_scene)} scenes, "
        f"{n} evaluated frames, {int(report.estimated.sum())} estimated. "
        f"<span class='muted'>Written {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC.</span></p>",
    ]
    parts += ["<h2>Metrics</h2>", _table(["metric", "value"], [[k, _fmt(k, v)] for k, v in report.metrics.items()])]
    if report.per_scene:
        keys = [
            ("Estimates for % of frames", "estimated"),
            ("Average Median Translation Error", "median t"),
            ("Average Median Rotation Error", "median R"),
            ("Precision @ VCRE < 90px", "prec. VCRE"),
            ("AUC @ VCRE < 90px", "AUC VCRE"),
        ]
        rows = [[s, *[_fmt(k, m.get(k)) for k, _ in keys]] for s, m in report.per_scene.items()]
        parts += ["<h2>Per scene</h2>", _table(["scene", *[h for _, h in keys]], rows)]
    parts += [
        "<h2>Figures</h2><div class='plots'>",
        *[_img(_fig_png(make(report)), caption) for _, caption, make in figures_of(report)],
        "</div>",
    ]
    cal = report.calibration()
    parts.append(
        "<h2>Calibration</h2><p>"
        + html.escape(format_calibration(cal, report.thresholds.vcre[0]) if cal else NOT_PROBABILITIES).replace(
            "\n", "<br>"
        )
        + "</p>"
    )
    parts += _worst_section(report, worst, figure, source_note)
    failed = int((~report.estimated).sum()) + report.extra_failures
    if failed:
        missing = sorted({str(s) for s in report.scene[~report.estimated]})
        parts.append(
            f"<h2>Frames without an estimate</h2><p>{failed} frame(s), in "
            f"{html.escape(', '.join(missing[:20]))}{' …' if len(missing) > 20 else ''}.</p>"
        )
    if report.problems:
        items = "".join(f"<li class='problem'>{html.escape(str(p))}</li>" for p in report.problems[:200])
        more = f"<p>… and {len(report.problems) - 200} more</p>" if len(report.problems) > 200 else ""
        parts += [f"<h2>Problems ({len(report.problems)})</h2><ul>{items}</ul>{more}"]
    page = (
        f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{_CSS}</style></head><body>{''.join(parts)}</body></html>\n"
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with naming(path):
        path.write_text(page, encoding="utf-8")
    return path

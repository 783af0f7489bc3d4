"""``mapfree evaluate``: exit statuses, a self-contained ``--html`` report small enough to mail, and the reports page's
example as printed."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapfree.cli import main


@pytest.fixture(scope="module")
def run_with_viz(synth, tmp_path_factory):
    """A run of the synthetic split with its figures (``run --viz``)."""
    from mapfree.cli import main

    d = tmp_path_factory.mktemp("runviz")
    assert (
        main(
            [
                "run",
                str(synth),
                "--method",
                "sift_pnp_sensor",
                "-o",
                str(d / "sub.zip"),
                "--no-progress",
                "--viz",
                str(d / "viz"),
            ]
        )
        == 0
    )
    return d


def _embedded_pictures(page: str) -> list[bytes]:
    """The plots (PNG) and the frames' figures (JPEG) embedded in a report page, in page order."""
    import base64
    import re

    return [base64.b64decode(b) for b in re.findall(r'src="data:image/(?:png|jpeg);base64,([^"]+)"', page)]


def test_evaluate_html_report_is_self_contained(synth, run_with_viz, tmp_path, capsys):
    import re

    from mapfree.cli import main

    sub, viz = run_with_viz / "sub.zip", run_with_viz / "viz"
    page_path = tmp_path / "out" / "report.html"
    assert main(["evaluate", str(sub), "--dataset", str(synth), "--html", str(page_path), "--viz", str(viz)]) == 0
    page = page_path.read_text()
    assert "AUC @ VCRE &lt; 90px" in page and "s00000" in page and "s00001" in page  # tables
    assert not re.search(r'(src|href)="(?!data:)', page)  # nothing fetched from elsewhere
    pics = _embedded_pictures(page)
    assert len(pics) == 3 + 4 and all(p.startswith(b"\x89PNG") for p in pics[:3])  # 3 plots, 4 scored frames
    assert all(p.startswith(b"\xff\xd8\xff") for p in pics[3:])  # the frames as JPEG
    # The worst frames' pictures are the run's own figures (matches + AR check), byte for byte (small enough).
    figs = {p.read_bytes() for p in viz.rglob("*.jpg")}
    assert set(pics[3:]) == figs
    # Without the run's figures, the AR check is drawn from the dataset's images.
    assert main(["evaluate", str(sub), "--dataset", str(synth), "--html", str(tmp_path / "r2.html")]) == 0
    pics2 = _embedded_pictures((tmp_path / "r2.html").read_text())
    assert len(pics2) == 7 and not set(pics2[3:]) & figs
    capsys.readouterr()


def test_evaluate_exit_codes_plots_file_and_track_mixup(synth, run_with_viz, tmp_path, capsys):
    from mapfree.benchmark import write_submission
    from mapfree.cli import main

    sub = run_with_viz / "sub.zip"
    base = ["evaluate", str(sub), "--dataset", str(synth)]
    (tmp_path / "afile").write_text("")
    assert main([*base, "--plots", str(tmp_path / "afile")]) == 1
    err = capsys.readouterr().err
    assert err.strip() == f"mapfree evaluate: error: --plots {tmp_path / 'afile'}: not a folder (it names a file)"
    assert main([*base, "--strict"]) == 0  # every scored frame estimated, no problem
    capsys.readouterr()
    write_submission(tmp_path / "empty.zip", {})
    assert main(["evaluate", str(tmp_path / "empty.zip"), "--dataset", str(synth)]) == 3
    assert "no scored frame has an estimate" in capsys.readouterr().err
    # A multi-frame submission scored on the single-frame track: said, not silent zeros.
    multi = tmp_path / "multi.zip"
    assert (
        main(["run", str(synth), "--track", "multi", "--method", "sift_pnp_sensor", "-o", str(multi), "--no-progress"])
        == 0
    )
    capsys.readouterr()
    assert main(["evaluate", str(multi), "--dataset", str(synth)]) == 3
    assert "score it with --track multi" in capsys.readouterr().err
    assert main(["evaluate", str(multi), "--dataset", str(synth), "--track", "multi"]) == 0


@pytest.mark.slow
def test_realmini_report_fits_in_a_mail(realmini, tmp_path, capfd):
    """`evaluate --html` was 14.1 MB on realmini-dev (full-size base64 PNGs); `run --viz` 1.3 MB a frame."""
    sub, viz, page = tmp_path / "sub.zip", tmp_path / "viz", tmp_path / "report.html"
    assert (
        main(["run", str(realmini), "--method", "sift_pnp_sensor", "-o", str(sub), "--viz", str(viz), "--no-progress"])
        == 0
    )
    figs = sorted(viz.rglob("*.jpg"))
    assert len(figs) == 20 and not list(viz.rglob("*.png"))
    import cv2

    assert all(max(cv2.imread(str(f)).shape[:2]) <= 1280 and f.stat().st_size < 400_000 for f in figs)
    assert main(["evaluate", str(sub), "--dataset", str(realmini), "--html", str(page), "--viz", str(viz)]) == 0
    assert page.stat().st_size < 2_000_000
    assert page.read_text().count('src="data:image/jpeg;base64,') == 8  # the eight worst frames
    capfd.readouterr()


@pytest.mark.slow
def test_the_reports_page_example_runs_as_printed(tmp_path):
    """The "Try it" block of docs/reports.md, run as a reader would, prints the statuses its comments say."""
    import os
    import re
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[1]
    block = re.findall(r"```bash\n(.*?)```", (repo / "docs" / "reports.md").read_text(), re.S)[-1]
    env = {
        **os.environ,
        "PYTHONPATH": str(repo / "src"),
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
    }
    p = subprocess.run(["bash", "-c", block], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    lines = p.stdout.splitlines()
    assert [ln for ln in lines if ln in ("0", "3")] == ["0", "3"], p.stdout + p.stderr
    assert (tmp_path / "out" / "report.html").is_file() and (tmp_path / "out" / "none.zip").is_file()
    assert "Traceback" not in p.stderr

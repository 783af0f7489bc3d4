"""Helpers shared by the tests of what the commands print (a module the tests import, not a test module)."""

from __future__ import annotations

from pathlib import Path


def one_line(capfd) -> tuple[str, str]:
    """(stdout, the only line of stderr); fails when stderr holds anything else (a traceback, a warning)."""
    out, err = capfd.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return out, lines[0]


def query_pair(synth: Path) -> tuple[str, str]:
    scene = synth / "val" / "s00000"
    return str(scene / "seq0" / "frame_00000.jpg"), str(scene / "seq1" / "frame_00005.jpg")

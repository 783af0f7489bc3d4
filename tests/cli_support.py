"""Helpers shared by the tests of what the commands print (a module the tests import, not a test module)."""

from __future__ import annotations

import os
import subprocess
import sys
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


def mapfree_process(
    *args: object, env: dict[str, str] | None = None, timeout: float = 300
) -> subprocess.CompletedProcess:
    """``python -m mapfree ARGS`` as its own process, as a user runs it; ``env`` is added to this process's."""
    return subprocess.run(
        [sys.executable, "-m", "mapfree", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, **(env or {})},
    )

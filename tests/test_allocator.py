"""The heap stays warm once a relocalizing process set it up (``mapfree`` does at start, pool and Ray workers when
they start): per-pair buffers of matching size are not faulted in again."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

# In a fresh process (the heap state of the test runner is whatever earlier tests left): set the process up as the
# command line does at start (``keep_heap_warm``) and build the SIFT method, then a few rounds of what one SIFT extraction does to the heap (the first octave's 16 Gaussian and DoG levels
# of a 540 x 360 image upsampled 2x, 3 MB each, alive together, then all freed), counting the minor page faults
# of the last rounds.
PROBE = """
import json, resource, sys
import numpy as np
from mapfree.relocalize import Relocalizer
from mapfree.relocalize.allocator import keep_heap_warm
if sys.argv[1] == "build":
    keep_heap_warm()
    Relocalizer.from_method("sift_emat_sensor")
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
counts = []
for _ in range(5):
    f = faults()
    levels = [np.full((720, 1080), 1.0, np.float32) for _ in range(16)]
    del levels
    counts.append(faults() - f)
print(json.dumps({"warm": keep_heap_warm(), "faults": counts[2:]}))
"""


def _probe(mode: str, **env: str) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", PROBE, mode],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "MAPFREE_OFFLINE": "1", **env},
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_relocalizer_keeps_heap_warm():
    r = _probe("build")
    assert r["warm"] is True
    assert max(r["faults"]) < 200  # the 50 MB faulted in again would be ~12 000 faults (4 KiB pages)
    # Opting out restores glibc's defaults, where the same matrix is given back and faulted in every round.
    cold = _probe("build", MAPFREE_MALLOC_DEFAULTS="1")
    assert cold["warm"] is False and min(cold["faults"]) > 1000


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_the_command_line_sets_the_heap_up_and_a_relocalizer_leaves_it():
    """The process-wide setting is made where a relocalizing process starts (``mapfree run`` here), not by building
    a Relocalizer."""
    code = (
        "import json\n"
        "from mapfree.relocalize import Relocalizer, allocator\n"
        "Relocalizer.from_method('sift_emat_sensor')\n"
        "built = allocator._done\n"
        "from mapfree.cli import main\n"
        "main(['run', '--list-methods'])\n"
        "print(json.dumps({'built': built, 'cli': allocator._done}))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {"built": None, "cli": True}

"""The reliability diagram of calibration files' held-out figures (docs/assets/calibration-reliability.png).

Usage:

    python bench/plot_calibrations.py OUT.png FILE.calib.json [FILE.calib.json ...]

Each file's cross-validated bins (``figures.p_correct``) are drawn as one curve, labelled with the method.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from mapfree.benchmark.plots import reliability_diagram
from mapfree.benchmark.reliability import reliability_from_dict


def main() -> None:
    out, files = Path(sys.argv[1]), sys.argv[2:]
    curves = {}
    for f in files:
        d = json.loads(Path(f).read_text())
        curves[d["method"]] = reliability_from_dict(d["figures"]["p_correct"])
    fig = reliability_diagram(curves, "VCRE < 90 px (held out)")
    fig.savefig(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""The 7-Scenes table of docs/benchmarks.md: realmini-dev's three HoloLens scenes in the 7-Scenes layout, K = 1 vs 10.

python bench/sevenscenes_realmini.py ../shared/data/realmini-dev OUT
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from mapfree.cli import main  # noqa: E402
from realmini_layouts import seven_scenes  # noqa: E402

CAMERA = ["495.567757", "495.481963", "269.502897", "169.194112"]  # realmini-dev's HoloLens intrinsics


def run(realmini: Path, out: Path) -> None:
    shutil.rmtree(out, ignore_errors=True)
    root = seven_scenes(realmini, out / "7scenes", {s: s for s in ("s00000", "s00001", "s00002")})
    for method, ks, mode in (("sift_pnp_depth", "1,10", "retrieval"), ("sift_emat_none", "10", "triangulation")):
        t0 = time.perf_counter()
        main(
            [
                "sevenscenes",
                str(root),
                "--method",
                method,
                "--k",
                ks,
                "--mode",
                mode,
                "--mapping-stride",
                "1",
                "--query-stride",
                "1",
                "--intrinsics",
                *CAMERA,
                "--out",
                str(out / mode),
                "--no-progress",
            ]
        )
        print(f"{method} {mode}: {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    run(
        Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/realmini-dev"),
        Path(sys.argv[2] if len(sys.argv) > 2 else "sevenscenes-realmini"),
    )

"""Full-size, randomly initialised SuperGlue (indoor and outdoor) and EfficientLoFTR models of the published
configurations (transformers' default configs), saved as ``$MAPFREE_WEIGHTS_DIR`` folders, for timing the
``superglue*`` and ``efficientloftr`` matchers where the real weights cannot be downloaded.

    python bench/hub_random_models.py DIR
    MAPFREE_WEIGHTS_DIR=DIR python bench/bench_pipeline.py --presets superglue_emat_sensor,efficientloftr_emat_sensor

The networks' cost is that of the real ones: SuperPoint still keeps its 1024 best points (a random detector puts
a score above the 0.005 threshold nearly everywhere) and SuperGlue's work is fixed by that count. EfficientLoFTR's
coarse stage is fixed by the image size; its fine stage grows with the number of coarse matches, which random
weights leave small, so its figure is a slight underestimate. The poses are meaningless.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def write_models(dst: Path, seed: int = 0) -> list[Path]:
    import torch
    from transformers import (
        EfficientLoFTRConfig,
        EfficientLoFTRForKeypointMatching,
        SuperGlueConfig,
        SuperGlueForKeypointMatching,
    )

    out = []
    for folder, make in (
        ("superglue_outdoor", lambda: SuperGlueForKeypointMatching(SuperGlueConfig())),
        ("superglue_indoor", lambda: SuperGlueForKeypointMatching(SuperGlueConfig())),
        ("efficientloftr", lambda: EfficientLoFTRForKeypointMatching(EfficientLoFTRConfig())),
    ):
        torch.manual_seed(seed)
        net = make()
        net.save_pretrained(dst / folder)
        n = sum(p.numel() for p in net.parameters())
        print(f"{dst / folder}: {n / 1e6:.1f} M parameters")
        out.append(dst / folder)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dst", type=Path, help="folder to fill (use it as $MAPFREE_WEIGHTS_DIR)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    write_models(args.dst, args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``mapfree match IMG0 IMG1 --matcher NAME``: correspondences between two photos, saved as ``.npz``."""

from __future__ import annotations

import argparse
from pathlib import Path

from . import HelpFormatter

DESCRIPTION = """\
Match two images with any registered matcher and print one line: the matcher, the number of matches and
the time it took. Keypoints are in the images' original pixels whatever size the matcher works at.

-o writes the matches as .npz with the same keys for every matcher: kpts0, kpts1 ((N,2) float32 x,y pixels),
scores ((N,) float32), image0, image1 (paths), size0, size1 (width,height), matcher, seconds.
--viz draws them side by side. Matchers whose weights are not installed say where to get them.
"""

EPILOG = """\
examples:
  mapfree match a.jpg b.jpg --matcher sift -o matches.npz --viz matches.png
  mapfree match a.jpg b.jpg --matcher xfeat --option top_k=2048
  mapfree match a.jpg b.jpg --matcher superglue --device cuda -o sg.npz
  mapfree match a.jpg b.jpg --matcher mast3r --backend onnxruntime --onnx mast3r.onnx
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "match",
        help="correspondences between two photos with any matcher (.npz)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=HelpFormatter,
    )
    p.add_argument("image0", type=Path, help="first image (the reference)")
    p.add_argument("image1", type=Path, help="second image (the query)")
    p.add_argument("--matcher", default="sift", help="matcher name (default: sift); see `mapfree run --list-methods`")
    p.add_argument("-o", "--output", type=Path, help="write the matches to this .npz file")
    p.add_argument("--viz", type=Path, help="draw the matches into this .png (or .jpg) file")
    p.add_argument("--device", help="cpu, cuda, cuda:1 … (default: cuda when available); not for sift")
    p.add_argument(
        "--backend",
        choices=("torch", "onnxruntime"),
        help="how a MASt3R-family network runs: torch (default) or onnxruntime (graphs of `mapfree export`)",
    )
    p.add_argument(
        "--onnx",
        type=Path,
        help="with --backend onnxruntime: the encoder graph (default: NAME.onnx in the weights folder)",
    )
    p.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a matcher option (e.g. max_keypoints=1024, weights=DIR); values read as YAML scalars",
    )
    p.set_defaults(func=run)


def _options(args: argparse.Namespace) -> dict:
    import yaml

    opts: dict = {}
    for item in args.option:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--option {item!r}: expected KEY=VALUE")
        try:
            opts[key.strip()] = yaml.safe_load(value) if value.strip() else None
        except yaml.YAMLError:
            raise ValueError(f"--option {item!r}: the value is not a YAML scalar") from None
    if args.device:
        opts["device"] = args.device
    if args.backend:
        opts["backend"] = args.backend
    if args.onnx is not None:
        if args.backend != "onnxruntime":
            raise ValueError("--onnx names a graph for --backend onnxruntime; add it")
        opts["onnx"] = str(args.onnx)
    return opts


def run(args: argparse.Namespace) -> int:
    from ..data import FormatError
    from ..matching import MissingWeightsError, check_options
    from ..matching.export import match_files, save_npz
    from ..options import check_device
    from . import fail, output_file_problem

    problem = (output_file_problem("-o", args.output) if args.output else None) or (
        output_file_problem("--viz", args.viz, (".png", ".jpg", ".jpeg")) if args.viz else None
    )
    if problem:
        return fail("match", problem)
    try:
        check_device(args.device)
        opts = _options(args)
        check_options(args.matcher, opts)  # before any image is read or weights loaded
        r = match_files(args.image0, args.image1, args.matcher, **opts)
    except (FormatError, MissingWeightsError, KeyError, ValueError, ImportError) as e:
        return fail("match", e)
    where = []
    if args.output:
        where.append(str(save_npz(args.output, r)))
    if args.viz:
        from ..data import read_image
        from ..viz import draw_matches, save_png

        m = r.matches
        where.append(
            str(save_png(args.viz, draw_matches(read_image(args.image0), read_image(args.image1), m.kpts0, m.kpts1)))
        )
    print(
        f"{r.matcher}: {len(r.matches)} matches ({r.keypoints[0]} / {r.keypoints[1]} points) in {r.seconds:.2f} s "
        f"(+{r.load_seconds:.2f} s loading)" + (f" -> {', '.join(where)}" if where else "")
    )
    return 0

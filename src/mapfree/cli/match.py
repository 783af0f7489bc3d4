"""``mapfree match IMG0 IMG1 --matcher NAME``: correspondences between two photos, saved as ``.npz``."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from . import HelpFormatter

DESCRIPTION = """\
Match two images with any registered matcher and print one line: the matcher, the number of matches and
the time it took. Keypoints are in the images' original pixels whatever size the matcher works at.

-o writes the matches as .npz with the same keys for every matcher: kpts0, kpts1 ((N,2) float32 x,y pixels),
scores ((N,) float32), image0, image1 (paths), size0, size1 (width,height), matcher, seconds.
--viz draws them side by side, green where they pass an essential-matrix check (MAGSAC++, 3 px) and red where
not; the check needs each image's intrinsics: --K-ref/--K-query fx,fy,cx,cy (pixels), else the photo's EXIF focal
length, else a default camera of 64 degrees across the long side. Matchers whose weights are not installed say
where to get them.
"""

EPILOG = """\
examples:
  mapfree match a.jpg b.jpg --matcher sift -o matches.npz --viz matches.png
  mapfree match a.jpg b.jpg --matcher xfeat --option top_k=2048
  mapfree match a.jpg b.jpg --matcher superglue --device cuda -o sg.npz
  mapfree match a.jpg b.jpg --matcher dune-mast3r --size 518 -o dune.npz
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
    from ..matching import names

    p.add_argument(
        "--matcher",
        default="sift",
        help=f"matcher name (default: sift): {', '.join(names())}; see `mapfree run --list-methods` for what each "
        "needs",
    )
    p.add_argument("-o", "--output", type=Path, help="write the matches to this .npz file")
    p.add_argument("--viz", type=Path, help="draw the matches into this .png (or .jpg) file")
    p.add_argument("--K-ref", help="intrinsics of image0 for --viz's check: fx,fy,cx,cy (pixels); default: EXIF")
    p.add_argument("--K-query", help="intrinsics of image1 for --viz's check: fx,fy,cx,cy (pixels); default: EXIF")
    p.add_argument("--device", help="cpu, cuda, cuda:1 … (default: cuda when available); not for sift")
    p.add_argument(
        "--size",
        type=int,
        metavar="PIXELS",
        help="long side of the network input, for the MASt3R family (mast3r, dust3r, dune-mast3r, "
        "dune-mast3r-small: the option long_side; default: the published size, 512 or DUNE's 518)",
    )
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
    if args.size is not None:
        opts["long_side"] = args.size
    if args.backend:
        opts["backend"] = args.backend
    if args.onnx is not None:
        if args.backend != "onnxruntime":
            raise ValueError("--onnx names a graph for --backend onnxruntime; add it")
        opts["onnx"] = str(args.onnx)
    return opts


def _checked_figure(views: tuple, m) -> tuple:
    """The --viz figure: matches green where they pass the essential-matrix check with the images' intrinsics
    (given, EXIF or default), red elsewhere; and the words the printed line adds."""
    import cv2
    import numpy as np

    from ..solvers.common import SolverError
    from ..solvers.essential import EssentialOptions, relative_pose_opencv
    from ..viz import draw_matches

    v0, v1 = views
    passed = np.zeros(len(m), bool)
    if len(m) >= 5:
        x0, x1 = (
            cv2.undistortPoints(k.reshape(-1, 1, 2).astype(np.float64), v.intrinsics.K, None).reshape(-1, 2)
            for k, v in ((m.kpts0, v0), (m.kpts1, v1))
        )
        thr = 3.0 / np.mean([v0.intrinsics.mean_focal, v1.intrinsics.mean_focal])
        with contextlib.suppress(SolverError):
            passed = relative_pose_opencv(x0, x1, EssentialOptions(), thr)[3]
    sources = f"intrinsics {v0.intrinsics_source}/{v1.intrinsics_source}"
    label = f"{len(m)} matches, {int(passed.sum())} pass the essential-matrix check ({sources})"
    return draw_matches(
        v0.image, v1.image, m.kpts0, m.kpts1, passed, label=label
    ), f"{int(passed.sum())} pass the check, {sources}"


def run(args: argparse.Namespace) -> int:
    from ..data import FormatError
    from ..matching import MissingWeightsError, check_options
    from ..matching.export import match_files, save_npz
    from ..options import check_device
    from . import fail, output_file_problem
    from .relocalize import InputError, k_flag

    try:  # a malformed --K-* flag first: before any file or data problem
        flags = (k_flag(args.K_ref, "--K-ref"), k_flag(args.K_query, "--K-query"))
    except InputError as e:
        return fail("match", e)
    problem = (output_file_problem("-o", args.output) if args.output else None) or (
        output_file_problem("--viz", args.viz, (".png", ".jpg", ".jpeg")) if args.viz else None
    )
    if problem:
        return fail("match", problem)
    try:
        check_device(args.device)
        opts = _options(args)
        check_options(args.matcher, opts)  # before any image is read or weights loaded
        views = None
        if args.viz:  # the images with their intrinsics (given ones checked) before any matching
            from ..relocalize import photo_views

            views = photo_views(args.image0, args.image1, flags, what=("--K-ref", "--K-query"))
        r = match_files(args.image0, args.image1, args.matcher, **opts)
    except (FormatError, MissingWeightsError, KeyError, ValueError, ImportError) as e:
        return fail("match", e)
    where = []
    if args.output:
        where.append(str(save_npz(args.output, r)))
    if views is not None:  # --viz
        from ..viz import save_png

        fig, words = _checked_figure(views, r.matches)
        where.append(f"{save_png(args.viz, fig)} ({words})")
    print(
        f"{r.matcher}: {len(r.matches)} matches ({r.keypoints[0]} / {r.keypoints[1]} points) in {r.seconds:.2f} s "
        f"(+{r.load_seconds:.2f} s loading)" + (f" -> {', '.join(where)}" if where else "")
    )
    return 0

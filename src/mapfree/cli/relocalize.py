"""``mapfree relocalize REF QUERY``: metric pose of one photo relative to another, as JSON."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..method_names import BEST_OFFLINE

if TYPE_CHECKING:
    from ..estimate import Estimate
    from ..geometry import Pose
    from ..localizer import Localizer
    from ..methods import Method
    from ..relocalize import View

DESCRIPTION = """\
Estimate the metric 6-DoF pose of QUERY relative to REF (X_query = R X_ref + t) and print it as JSON
(pose, confidence, inliers, per-stage timings, or the reason there is no estimate).
Exit status: 0 pose estimated, 1 error, 3 no estimate (the JSON says why).

Intrinsics, per image, in this order (the JSON's "intrinsics" says which): given with --K-ref/--K-query,
--intrinsics (a Map-free intrinsics.txt) or, for images inside a Map-free scene folder, that scene's
intrinsics.txt; else the photo's EXIF focal length (35 mm-equivalent: f = f35 / 36 mm x the long side; or
FocalLength with the sensor's pixel density); else the method's own estimate (MASt3R/DUSt3R pointmaps); else a
default camera of 64 degrees across the long side, with a warning. Depth comes from --depth-ref/--depth-query
(uint16 PNG, millimetres) or from the method's depth source (e.g. files:sensor reads FRAME.sensor.png).
"""

EPILOG = """\
examples:
  mapfree relocalize scene/seq0/frame_00000.jpg scene/seq1/frame_00010.jpg --method sift_emat_sensor --gt-pose auto
  mapfree relocalize a.jpg b.jpg --K-ref 500,500,270,180 --K-query 500,500,270,180 \\
      --depth-ref a_depth.png --depth-query b_depth.png --viz out.png
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "relocalize",
        help="relative metric pose between two photos (JSON)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("reference", type=Path, help="reference image")
    p.add_argument("query", type=Path, help="query image")
    p.add_argument(
        "--method",
        default=BEST_OFFLINE,
        help=f"preset name, YAML config or path (default: {BEST_OFFLINE}); see `mapfree run --list-methods`",
    )
    p.add_argument("--depth", default=None, help="override the method's depth: files:SUFFIX, none, hf:MODEL")
    p.add_argument("--intrinsics", type=Path, help="Map-free intrinsics.txt holding lines for both images")
    p.add_argument("--K-ref", help="reference intrinsics fx,fy,cx,cy (pixels)")
    p.add_argument("--K-query", help="query intrinsics fx,fy,cx,cy (pixels)")
    p.add_argument("--depth-ref", type=Path, help="reference depth map (uint16 PNG, mm)")
    p.add_argument("--depth-query", type=Path, help="query depth map (uint16 PNG, mm)")
    p.add_argument(
        "--gt-pose",
        help="ground truth: 'qw,qx,qy,qz,tx,ty,tz' (query w.r.t. reference), "
        "a poses.txt holding both frames, or 'auto' (the scene's poses.txt)",
    )
    p.add_argument("--viz", type=Path, help="draw the matches and the AR check into this .png (or .jpg) file")
    p.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="weights of a regression method (e.g. --method rpr-3d3d --checkpoint 3d3d.ckpt)",
    )
    p.add_argument(
        "--calibration",
        type=Path,
        default=None,
        metavar="FILE",
        help="calibration file of the method (`mapfree calibrate`): the answer gets p_correct, the probability "
        "that the pose is within 90 px (default: the preset's shipped calibration, if any)",
    )
    p.set_defaults(func=run)


class InputError(Exception):
    pass


def _floats(text: str, n: int, what: str) -> list[float]:
    import numpy as np

    try:
        vals = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        raise InputError(f"{what}: expected {n} comma-separated numbers, got {text!r}") from None
    if len(vals) != n or not all(np.isfinite(vals)):
        raise InputError(f"{what}: expected {n} finite comma-separated numbers, got {text!r}")
    return vals


def _scene_dir(image: Path) -> Path:
    """``scene/seqN/frame.jpg`` -> ``scene``."""
    return image.resolve().parent.parent


def _frame_name(image: Path) -> str:
    p = image.resolve()
    return f"{p.parent.name}/{p.name}"


def _lookup(table: dict, image: Path, source: Path):
    """A per-frame entry for ``image``: by ``seqN/frame`` name, else by a unique base name."""
    name = _frame_name(image)
    if name in table:
        return table[name]
    hits = [v for k, v in table.items() if Path(k).name == image.name]
    if len(hits) == 1:
        return hits[0]
    raise InputError(f"{source}: no unique entry for {name}")


def k_flag(text: str | None, what: str) -> list[float] | None:
    """``fx,fy,cx,cy`` of a --K-* flag (None when not given), checked before anything else is looked at."""
    if not text:
        return None
    vals = _floats(text, 4, what)
    if vals[0] <= 0 or vals[1] <= 0:
        raise InputError(f"{what}: focal lengths must be positive")
    return vals


def _given_intrinsics(args, image: Path, flag: list[float] | None, what: str):
    """The intrinsics given for ``image`` (its --K-* flag, --intrinsics, or its Map-free scene's
    intrinsics.txt), principal point checked; None when none are given (EXIF, the method or the default then)."""
    from ..data import read_image, read_intrinsics
    from ..data.intrinsics import check_principal_point
    from ..geometry import Intrinsics

    if flag:
        h, w = read_image(image).shape[:2]
        check_principal_point(flag[2], flag[3], w, h, what)
        return Intrinsics(flag[0], flag[1], flag[2], flag[3], w, h)
    if args.intrinsics is not None and not args.intrinsics.is_file():
        raise InputError(f"intrinsics file {args.intrinsics} not found")
    source = args.intrinsics or _scene_dir(image) / "intrinsics.txt"
    if not source.is_file():
        return None
    K = _lookup(read_intrinsics(source), image, source)
    check_principal_point(K.cx, K.cy, K.width, K.height, f"{source}: {image.name}")
    return K


def _gt_pose(args: argparse.Namespace) -> Pose | None:
    from ..data import read_poses
    from ..geometry import Pose

    if not args.gt_pose:
        return None
    if args.gt_pose == "auto" or Path(args.gt_pose).is_file():
        source = _scene_dir(args.query) / "poses.txt" if args.gt_pose == "auto" else Path(args.gt_pose)
        if not source.is_file():
            raise InputError(f"--gt-pose auto: {source} not found")
        table = read_poses(source).as_dict()
        p_ref, p_q = _lookup(table, args.reference, source), _lookup(table, args.query, source)
        if p_ref is None or p_q is None:
            raise InputError(f"{source}: no ground truth for these frames (all-zero lines)")
        return p_q.relative_to(p_ref)
    v = _floats(args.gt_pose, 7, "--gt-pose")
    try:
        return Pose.from_qt(v[:4], v[4:])
    except ValueError as e:
        raise InputError(f"--gt-pose: {e}") from None


def _query_has_depth(method, args) -> bool:
    """Whether the query will have a depth map: given, predicted by a network, or a ``files:`` map beside it."""
    if args.depth_query is not None or method.kind != "matching" or not method.depth.startswith("files:"):
        return True
    from ..data.io import depth_path_for

    return depth_path_for(args.query, method.depth.split(":", 1)[1]).is_file()


def _check_depth_suffix(method, args) -> None:
    """A ``files:SUFFIX`` method whose map is not beside the reference (and no --depth-ref) is a typo in the suffix
    or the method, not a pair without depth: refused, naming the suffixes that are there (as ``mapfree run``)."""
    if method.kind != "matching" or not method.depth.startswith("files:") or args.depth_ref is not None:
        return
    from ..data.io import depth_path_for, depth_suffixes

    suffix = method.depth.split(":", 1)[1]
    if not args.reference.is_file() or depth_path_for(args.reference, suffix).is_file():
        return
    found = depth_suffixes(args.reference)
    raise InputError(
        f"method {method.name!r} reads depth maps *.{suffix}.png, but the reference has none "
        f"({depth_path_for(args.reference, suffix)}); depth suffixes there: {', '.join(found) or 'none'} "
        f"(pick one with NAME@SUFFIX or the method's last part, or pass --depth-ref)"
    )


def run(args: argparse.Namespace) -> int:
    from ..data import FormatError
    from ..relocalize import default_warning
    from . import EXIT_NOTHING, fail, output_file_problem

    try:  # a malformed --K-* flag first: before any file or data problem
        k_flags = (k_flag(args.K_ref, "--K-ref"), k_flag(args.K_query, "--K-query"))
    except InputError as e:
        return fail("relocalize", e)
    problem = output_file_problem("--viz", args.viz, (".png", ".jpg", ".jpeg")) if args.viz else None
    if problem:
        return fail("relocalize", problem)
    try:
        method = _method(args)
        loc, views, gt = _inputs(args, method, k_flags)
    except (InputError, FormatError, FileNotFoundError, KeyError, ValueError) as e:
        return fail("relocalize", e)

    ref, query = views
    if method.kind == "matching":  # a regression network does not use the intrinsics for its pose
        for v in views:
            if (warning := default_warning(v)) is not None:
                print(f"mapfree relocalize: warning: {warning}", file=sys.stderr)
    est = loc.relocalize(ref, query)
    from ..calibration import calibration_for

    calibration = calibration_for(method.name, method.options)
    if calibration is not None and est.p_correct is None:
        calibration.apply(est)
    print(json.dumps(_answer(args, method, est, views, gt), indent=2, allow_nan=False))
    if est.pose is None:
        print(f"mapfree relocalize: no estimate: {est.reason}", file=sys.stderr)
        return EXIT_NOTHING
    return 0


def _method(args: argparse.Namespace) -> Method:
    """The method the flags name (``--method``, ``--checkpoint``, ``--depth``, ``--calibration``), refused when it
    cannot run on this pair's depth, or its PnP twin for a query without the depth map its solver needs."""
    from ..methods import depth_free_problem, get, query_depth_fallback

    if args.checkpoint is not None:
        from .run import _with_checkpoint

        method = _with_checkpoint(args.method, args.checkpoint)
    else:
        method = get(args.method)
    if args.depth:
        method = method.with_depth(args.depth)
    _check_depth_suffix(method, args)
    problem = depth_free_problem(method)
    if problem and (args.depth_ref is None or (method.solver == "procrustes" and args.depth_query is None)):
        raise InputError(f"{problem}; or pass the maps with --depth-ref/--depth-query")
    if not _query_has_depth(method, args):
        fallback = query_depth_fallback(method)
        if fallback is not method:
            print(
                f"mapfree relocalize: {args.query} has no depth map ({method.depth}): {method.name} runs with "
                f"PnP instead (reference depth only)",
                file=sys.stderr,
            )
            method = fallback
    if args.calibration is not None:
        from ..relocalize.calibrate import with_calibration

        method = with_calibration(method, [args.calibration])
    return method


def _inputs(
    args: argparse.Namespace, method: Method, k_flags: tuple[list[float] | None, list[float] | None]
) -> tuple[Localizer[Any], tuple[View, View], Pose | None]:
    """The built method, the two images as views (intrinsics and depth maps resolved) and the ground truth."""
    from ..data import check_depth_size, read_depth
    from ..relocalize import Relocalizer, build_localizer, photo_views

    for p in (args.reference, args.query):
        if not p.is_file():
            raise InputError(f"{p}: image not found")
    given = [
        _given_intrinsics(args, image, flag, what)
        for image, flag, what in ((args.reference, k_flags[0], "--K-ref"), (args.query, k_flags[1], "--K-query"))
    ]
    depths = [read_depth(p) if p else None for p in (args.depth_ref, args.depth_query)]
    gt = _gt_pose(args)
    loc = build_localizer(method)
    if args.depth_ref is None or args.depth_query is None:
        from ..relocalize.run import check_depth_source

        check_depth_source(loc)  # a depth network that cannot be loaded: one clear error, not a "no estimate"
    views = photo_views(
        args.reference,
        args.query,
        (given[0], given[1]),
        (depths[0], depths[1]),
        loc.matcher if isinstance(loc, Relocalizer) else None,  # its focal estimate, when it has one
        ("--K-ref", "--K-query"),
    )
    for v, dpath, depth in zip(views, (args.depth_ref, args.depth_query), depths):
        if depth is not None and v.frame is not None:
            check_depth_size(dpath, depth.shape, v.frame.intrinsics.width, v.frame.intrinsics.height)
    return loc, views, gt


def _answer(
    args: argparse.Namespace, method: Method, est: Estimate, views: tuple[View, View], gt: Pose | None
) -> dict[str, Any]:
    """The JSON printed: the estimate, the intrinsics used, the scores, the error against ``gt``, the figure."""
    import numpy as np

    from ..relocalize.run import estimate_scores

    ref, query = views
    out = {"method": method.name, "reference": str(args.reference), "query": str(args.query), **est.to_dict()}
    out["intrinsics"] = {"reference": ref.resolved.to_dict(), "query": query.resolved.to_dict()}
    out["scores"] = estimate_scores(est)
    if est.extras.get("same_viewpoint"):  # the query was taken from the reference's viewpoint: identity pose
        out["same_viewpoint"] = True
    if gt is not None and est.pose is not None:
        from ..geometry import rotation_angle_deg
        from ..viz import vcre_px

        out["error"] = {
            "translation_m": float(np.linalg.norm(est.pose.center - gt.center)),
            "rotation_deg": float(rotation_angle_deg(est.pose.R, gt.R)),
            "vcre_px": vcre_px(est.pose, gt, query.intrinsics),
        }
    if args.viz:
        from ..viz import estimate_figure, save_png

        thr = float(method.solver_opts.get("ransac_threshold_px", 3.0))
        fig = estimate_figure(
            ref.image, query.image, ref.intrinsics, query.intrinsics, est, gt, threshold_px=thr, title=method.name
        )
        out["viz"] = str(save_png(args.viz, fig))
    return out

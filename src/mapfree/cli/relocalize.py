"""``mapfree relocalize REF QUERY``: metric pose of one photo relative to another, as JSON."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..method_names import BEST_OFFLINE

if TYPE_CHECKING:
    from ..geometry import Pose

DESCRIPTION = """\
Estimate the metric 6-DoF pose of QUERY relative to REF (X_query = R X_ref + t) and print it as JSON
(pose, confidence, inliers, per-stage timings, or the reason there is no estimate).
Exit status: 0 pose estimated, 1 error, 3 no estimate (the JSON says why).

Intrinsics come from --K-ref/--K-query, from --intrinsics (a Map-free intrinsics.txt), or, for images
inside a Map-free scene folder, from that scene's intrinsics.txt. Depth comes from --depth-ref/--depth-query
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


def _intrinsics(args, image: Path, flag: str | None, optional: bool = False, what: str = "intrinsics"):
    from ..data import read_image, read_intrinsics
    from ..geometry import Intrinsics

    if optional and not flag and not args.intrinsics and not (_scene_dir(image) / "intrinsics.txt").is_file():
        h, w = read_image(image).shape[:2]  # regression ignores intrinsics: a nominal camera for the error report
        return Intrinsics(float(max(w, h)), float(max(w, h)), (w - 1) / 2, (h - 1) / 2, w, h)
    if flag:
        h, w = read_image(image).shape[:2]
        fx, fy, cx, cy = _floats(flag, 4, what)
        if fx <= 0 or fy <= 0:
            raise InputError(f"{what}: focal lengths must be positive")
        return Intrinsics(fx, fy, cx, cy, w, h)
    if args.intrinsics is not None and not args.intrinsics.is_file():
        raise InputError(f"intrinsics file {args.intrinsics} not found")
    source = args.intrinsics or _scene_dir(image) / "intrinsics.txt"
    if not source.is_file():
        raise InputError(f"no intrinsics for {image}: pass --K-ref/--K-query or --intrinsics FILE")
    return _lookup(read_intrinsics(source), image, source)


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
    import numpy as np

    from ..data import FormatError, check_depth_size, read_depth
    from ..methods import get
    from ..relocalize import Relocalizer, as_view
    from . import EXIT_NOTHING, fail, output_file_problem

    problem = output_file_problem("--viz", args.viz, (".png", ".jpg", ".jpeg")) if args.viz else None
    if problem:
        return fail("relocalize", problem)
    try:
        if args.checkpoint is not None:
            from .run import _with_checkpoint

            method = _with_checkpoint(args.method, args.checkpoint)
        else:
            method = get(args.method)
        if args.depth:
            method = method.with_depth(args.depth)
        from ..methods import depth_free_problem, query_depth_fallback

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
        for p in (args.reference, args.query):
            if not p.is_file():
                raise InputError(f"{p}: image not found")
        views = []
        for image, kflag, dpath, what in (
            (args.reference, args.K_ref, args.depth_ref, "--K-ref"),
            (args.query, args.K_query, args.depth_query, "--K-query"),
        ):
            K = _intrinsics(args, image, kflag, optional=method.kind == "regression", what=what)
            depth = read_depth(dpath) if dpath else None
            if depth is not None and K is not None:
                check_depth_size(dpath, depth.shape, K.width, K.height)
            v = as_view((image, K, depth))
            if v.image.shape[:2] != (v.intrinsics.height, v.intrinsics.width):
                raise InputError(
                    f"{image}: image is {v.image.shape[1]}x{v.image.shape[0]} but its intrinsics "
                    f"say {K.width}x{K.height}"
                )
            views.append(v)
        gt = _gt_pose(args)
        loc = Relocalizer.from_method(method)
        if args.depth_ref is None or args.depth_query is None:
            from ..relocalize.run import check_depth_source

            check_depth_source(loc)  # a depth network that cannot be loaded: one clear error, not a "no estimate"
    except (InputError, FormatError, FileNotFoundError, KeyError, ValueError) as e:
        return fail("relocalize", e)

    ref, query = views
    est = loc.relocalize(ref, query)
    from ..calibration import calibration_for

    calibration = calibration_for(method.name, method.options)
    if calibration is not None and est.p_correct is None:
        calibration.apply(est)
    out = {"method": method.name, "reference": str(args.reference), "query": str(args.query), **est.to_dict()}
    from ..relocalize.run import estimate_scores

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
    print(json.dumps(out, indent=2, allow_nan=False))
    if est.pose is None:
        print(f"mapfree relocalize: no estimate: {est.reason}", file=sys.stderr)
        return EXIT_NOTHING
    return 0

"""``mapfree run ROOT --split val --method NAME -o submission.zip``: relocalize a whole split."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..relocalize import RunResult
    from ..relocalize.multiframe import MultiRunResult

DESCRIPTION = """\
Relocalize every query the benchmark scores (every 5th; --all-frames for all) of every scene of a split
against the scene's reference image and write a submission ZIP.

Reference features and depth are computed once per scene; scenes run in parallel worker processes,
or, with --ray, as chunks of frames on the workers of a Ray cluster (same results, same journal).
Every finished frame is appended to OUTPUT's journal (submission.journal.jsonl): after a crash or
Ctrl-C, run the same command with --resume and only the missing frames are computed. Frames without an
estimate are listed with their reason in submission.failures.jsonl. Nothing non-finite is ever written.
A resumed scene whose data changed since it was journaled is computed again.

Exit status: 0 results written, 1 error, 3 nothing estimated (with --strict: a frame without an estimate).
"""

EPILOG = """\
examples:
  mapfree run data/ --split val --method sift_emat_dptkitti -o sift.zip --workers 2
  mapfree run data/ --split val --method best-offline -o best.zip --resume --evaluate
  mapfree run data/ --method configs/methods/xfeat-pnp-poselib.yaml --scenes s00000,s00001 --viz figures/
  mapfree run /shared/data --split test --method mast3r_pnp_mast3r -o /shared/m.zip --ray auto --gpus-per-task 1
  mapfree run --list-methods
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "run",
        help="relocalize a whole split into a submission ZIP (resumable)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("root", nargs="?", type=Path, help="Map-free dataset root (holding val/, test/ …)")
    p.add_argument("--split", default="val", help="split to run (default: val)")
    p.add_argument("--method", help="preset name ({matcher}_{solver}_{depth}), YAML config name or path")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        default=Path("submission.zip"),
        help="submission ZIP to write (default: submission.zip)",
    )
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes (over scenes; default: 1)")
    p.add_argument(
        "--batch",
        type=int,
        default=None,
        metavar="N",
        help="queries per GPU pass of the batched pipeline (background decoding, batched features and "
        "matching, solvers in a thread pool); 0: one pair at a time (default: 16 on a GPU, else 0)",
    )
    p.add_argument(
        "--all-frames", action="store_true", help="every query, not only the scored ones (single-frame track only)"
    )
    p.add_argument(
        "--references",
        type=int,
        default=1,
        metavar="K",
        help="represent each scene by K posed seq0 images chosen by K-means over DenseVLAD, and "
        "relocalize each query against the most similar (default: 1, the reference image)",
    )
    p.add_argument(
        "--reference-mode",
        default="retrieval",
        choices=("retrieval", "triangulation"),
        help="with --references K >= 2: 'triangulation' = the paper's depth-free baseline "
        "(relative directions to the two most similar references; default: retrieval)",
    )
    p.add_argument(
        "--track",
        default="single",
        choices=("single", "multi"),
        help="'multi': the multi-frame track — relocalize each scored query's 9-frame burst, fuse "
        "them through poses_device.txt (derived from ground truth with simulated drift when a "
        "scene has none); per-frame results go to OUTPUT.frames.zip (default: single)",
    )
    p.add_argument("--resume", action="store_true", help="continue the run journaled beside OUTPUT")
    p.add_argument("--overwrite", action="store_true", help="discard an existing journal and start again")
    p.add_argument("--scenes", help="comma-separated scene names (default: all)")
    p.add_argument(
        "--confidence",
        help="extra score to use as the submission confidence (e.g. confidence_inliers, confidence_score), or "
        "'calibrated': the probability that the pose is right (p_correct; see --calibration)",
    )
    p.add_argument(
        "--calibration",
        type=Path,
        action="append",
        default=[],
        metavar="FILE",
        help="calibration file of the method (`mapfree calibrate`): each estimate gets p_correct; a cascade "
        "takes one per stage (default: the preset's shipped calibration, if any)",
    )
    p.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="trained checkpoint for a regression method (e.g. --method rpr --checkpoint best.ckpt)",
    )
    p.add_argument(
        "--evaluate",
        action="store_true",
        help="score the submission against the split's poses (the table of `mapfree evaluate`)",
    )
    p.add_argument("--json", action="store_true", help="print the run's summary (and scores) as JSON")
    p.add_argument("--strict", action="store_true", help="exit 3 unless every frame got an estimate")
    p.add_argument(
        "--viz",
        type=Path,
        default=None,
        metavar="DIR",
        help="draw each frame computed (matches + AR check) as DIR/SCENE/seq1_frame_NNNNN.jpg "
        "(JPEG, long side <= 1280 px: about 150-300 KB a frame)",
    )
    p.add_argument(
        "--ray",
        nargs="?",
        const="local",
        default=None,
        metavar="ADDRESS",
        help="compute the frames on Ray workers: without ADDRESS on a Ray instance started here; "
        "'auto', HOST:PORT or ray://HOST:PORT joins a running cluster (every node must read ROOT "
        "at the same path)",
    )
    p.add_argument(
        "--cpus-per-task",
        type=float,
        default=None,
        metavar="N",
        help="with --ray: CPUs each worker asks for (default: 1)",
    )
    p.add_argument(
        "--gpus-per-task",
        type=float,
        default=None,
        metavar="N",
        help="with --ray: GPUs each worker asks for; a fraction such as 0.25 shares a GPU between "
        "workers (default: 1 for a method with networks on a cluster with GPUs, else 0)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--list-methods", action="store_true", help="print the method names, each with what it needs, and exit"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..data import FormatError
    from . import EXIT_ERROR, EXIT_NOTHING, fail

    if args.list_methods:
        return _list_methods()
    if args.root is None and args.ray not in (None, "local") and Path(args.ray).is_dir():
        args.root, args.ray = Path(args.ray), "local"  # `run --ray ROOT …`: the folder is ROOT, not an address
    problem = _usage_problem(args)
    if problem:
        return fail("run", problem)
    from ..relocalize.distributed import ClusterError
    from ..relocalize.multiframe import MultiRunResult

    try:
        res = _run(args)
    except (ClusterError, FileExistsError, FileNotFoundError, FormatError, KeyError, ValueError) as e:
        return fail("run", e)
    except KeyboardInterrupt:
        return _interrupted(args)
    frames = res.frames if isinstance(res, MultiRunResult) else res  # multi-frame: the per-frame run behind it
    _print_warnings(frames)
    out = res.to_dict()
    report, error = _evaluate(res, args, out) if args.evaluate else (None, None)
    if args.json:
        print(json.dumps(out, indent=2, allow_nan=False))
    else:
        _print_summary(res, frames, args)
        if report is not None:
            from ..benchmark import format_table

            print(format_table(report), end="")
    if error:
        print(error, file=sys.stderr)
        return EXIT_ERROR
    if res.estimated == 0 or (args.strict and res.failed):
        why = "no frame got an estimate" if res.estimated == 0 else f"{res.failed} frame(s) without an estimate"
        print(f"mapfree run: {why} (reasons in {res.failures})", file=sys.stderr)
        return EXIT_NOTHING
    return 0


def _list_methods() -> int:
    """``--list-methods``: each name with what it needs."""
    from ..methods import list_methods, requirements

    names = list_methods()
    width = max(map(len, names))
    print("\n".join(f"{n:<{width}}  {requirements(n)}" for n in names))
    return 0


def _usage_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with the command line before anything is read, or None."""
    if args.root is None or not args.method:
        return "ROOT and --method are required (or --list-methods)"
    if args.workers < 1:
        return "--workers must be >= 1"
    if args.batch is not None and args.batch < 0:
        return "--batch must be >= 0"
    if args.track == "multi" and args.all_frames:
        return (
            "--all-frames cannot be combined with --track multi (the multi-frame track runs the 9-frame "
            "bursts of the scored queries)"
        )
    if args.viz is not None and args.viz.exists() and not args.viz.is_dir():
        return f"--viz {args.viz}: not a folder (it names a file)"
    if args.scenes is not None and not [s for s in args.scenes.split(",") if s.strip()]:
        return f"--scenes {args.scenes!r}: no scene name (give e.g. --scenes s00000,s00001)"
    return None


def _method(args: argparse.Namespace) -> Any:
    """The method the flags name: ``--method`` with ``--checkpoint``, ``--references`` and ``--calibration``."""
    method = args.method
    if getattr(args, "checkpoint", None) is not None:
        method = _with_checkpoint(method, args.checkpoint)
    if args.references != 1 or args.reference_mode != "retrieval":
        from ..relocalize.references import with_references

        method = with_references(method, args.references, args.reference_mode)
    if args.calibration:
        from ..relocalize.calibrate import with_calibration

        method = with_calibration(method, args.calibration)
    return method


def _run(args: argparse.Namespace) -> RunResult | MultiRunResult:
    """The run the flags ask for: ``run_split``, or ``run_multi`` for ``--track multi``."""
    from ..relocalize import run_split
    from ..relocalize.multiframe import run_multi

    ray_options = _ray_options(args)
    run: Callable[..., RunResult | MultiRunResult] = run_multi if args.track == "multi" else run_split
    return run(
        args.root,
        args.split,
        _method(args),
        args.output,
        workers=args.workers,
        all_frames=args.all_frames,
        resume=args.resume,
        overwrite=args.overwrite,
        confidence=args.confidence,
        progress=not args.no_progress,
        scenes=[s.strip() for s in args.scenes.split(",") if s.strip()] if args.scenes else None,
        batch_size=args.batch,
        viz_dir=args.viz,
        ray_address=args.ray,
        ray_options=ray_options,
    )


def _interrupted(args: argparse.Namespace) -> int:
    """Ctrl-C: say how many frames the journal keeps for ``--resume``."""
    from ..relocalize.journal import journal_path, read_journal
    from ..relocalize.multiframe import frames_path

    jpath = journal_path(frames_path(args.output) if args.track == "multi" else args.output)
    print(
        f"mapfree run: interrupted; the {len(read_journal(jpath)[1])} finished frames are kept in {jpath}: "
        f"run the same command with --resume to continue",
        file=sys.stderr,
    )
    return 130


def _print_warnings(frames: RunResult) -> None:
    """Stale scenes computed again, torn journal lines dropped: one line each on stderr."""
    if frames.stale_scenes:
        print(
            f"mapfree run: the data of {', '.join(frames.stale_scenes)} changed since the journal was written: "
            f"computed again",
            file=sys.stderr,
        )
    if frames.torn_lines:
        print(
            f"mapfree run: {frames.journal}: {frames.torn_lines} line(s) cut mid-write (a kill or a full disk) "
            f"dropped; their frames were computed again",
            file=sys.stderr,
        )


def _evaluate(res: RunResult | MultiRunResult, args: argparse.Namespace, out: dict[str, Any]) -> tuple[Any, str | None]:
    """``--evaluate``: the report (its metrics added to ``out``), or the line saying why it cannot be scored."""
    from ..benchmark import EvaluationError, evaluate
    from ..data import FormatError

    try:
        report = evaluate(res.submission, args.root, args.split, track=args.track)
    except (EvaluationError, FormatError, FileNotFoundError, ValueError) as e:
        return None, (
            f"mapfree run: error: the submission {res.submission} was written but cannot be scored here: "
            f"{e}; score it with `mapfree evaluate {res.submission} --dataset {args.root} --split "
            f"{args.split} --gt-root GT` when you hold the ground truth"
        )
    out["metrics"] = report.metrics.to_dict()
    return report, None


def _print_summary(res, frames, args: argparse.Namespace) -> None:
    """What the run wrote, in a few lines (``--json`` prints everything)."""
    from . import plural

    total = res.estimated + res.failed
    print(
        f"wrote {res.submission}: {res.estimated} of {total} frames estimated "
        f"({frames.computed} computed, {frames.skipped} from the journal, {plural(frames.scenes, 'scene')}, "
        f"{frames.seconds:.1f} s)"
    )
    if res.failed:
        print(f"frames without an estimate and why: {res.failures}")
    if args.viz is not None and frames.computed:
        print(f"figures of the computed frames: {args.viz}/SCENE/")
    if frames.cluster:
        c = frames.cluster
        where = "a Ray instance on this machine" if c["address"] == "local" else f"the Ray cluster {c['address']}"
        print(
            f"computed on {where}: {c['workers']} workers on {c['nodes']} node(s)"
            + (f"; {c['requeued']} frame(s) of lost workers computed elsewhere" if c["requeued"] else "")
        )


def _ray_options(args: argparse.Namespace):
    """``RayOptions`` of ``--cpus-per-task``/``--gpus-per-task`` (which need ``--ray``); None without ``--ray``."""
    given = [
        f
        for f, v in (("--cpus-per-task", args.cpus_per_task), ("--gpus-per-task", args.gpus_per_task))
        if v is not None
    ]
    if args.ray is None:
        if given:
            raise ValueError(f"{given[0]} applies to a run on Ray: add --ray [ADDRESS]")
        return None
    if args.workers != 1:
        raise ValueError(
            "--workers sizes the local pool; on Ray the cluster's resources decide how many workers run "
            "(--cpus-per-task, --gpus-per-task)"
        )
    from ..relocalize.distributed import RayOptions

    return RayOptions(
        cpus_per_task=1.0 if args.cpus_per_task is None else args.cpus_per_task, gpus_per_task=args.gpus_per_task
    )


def _with_checkpoint(name: str, checkpoint: Path):
    """The method ``name`` with ``options.checkpoint`` set; only regression methods take a checkpoint."""
    import dataclasses

    from ..methods import get

    method = get(name)
    if method.kind != "regression":
        raise ValueError(f"--checkpoint is for regression methods, but {name!r} is a {method.kind} method")
    if not checkpoint.is_file():
        raise FileNotFoundError(f"checkpoint {checkpoint} not found")
    return dataclasses.replace(method, options={**method.options, "checkpoint": str(checkpoint)})

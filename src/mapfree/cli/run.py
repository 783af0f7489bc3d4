"""``mapfree run ROOT --split val --method NAME -o submission.zip``: relocalize a whole split."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

DESCRIPTION = """\
Relocalize every query the benchmark scores (every 5th; --all-frames for all) of every scene of a split
against the scene's reference image and write a submission ZIP.

Reference features and depth are computed once per scene; scenes run in parallel worker processes.
Every finished frame is appended to OUTPUT's journal (submission.journal.jsonl): after a crash or
Ctrl-C, run the same command with --resume and only the missing frames are computed. Frames without an
estimate are listed with their reason in submission.failures.jsonl. Nothing non-finite is ever written.
"""

EPILOG = """\
examples:
  mapfree run data/ --split val --method sift_emat_dptkitti -o sift.zip --workers 2
  mapfree run data/ --split val --method configs/methods/best-offline.yaml -o best.zip --resume --evaluate
  mapfree run --list-methods
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("run", help="relocalize a whole split into a submission ZIP (resumable)",
                              description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", nargs="?", type=Path, help="Map-free dataset root (holding val/, test/ …)")
    p.add_argument("--split", default="val", help="split to run (default: val)")
    p.add_argument("--method", help="preset name ({matcher}_{solver}_{depth}), YAML config name or path")
    p.add_argument("-o", "--output", type=Path, default=Path("submission.zip"),
                   help="submission ZIP to write (default: submission.zip)")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes (over scenes; default: 1)")
    p.add_argument("--batch", type=int, default=None, metavar="N",
                   help="queries per GPU pass of the batched pipeline (background decoding, batched features and "
                        "matching, solvers in a thread pool); 0: one pair at a time (default: 16 on a GPU, else 0)")
    p.add_argument("--all-frames", action="store_true",
                   help="every query, not only the scored ones (single-frame track only)")
    p.add_argument("--references", type=int, default=1, metavar="K",
                   help="represent each scene by K posed seq0 images chosen by K-means over DenseVLAD, and "
                        "relocalize each query against the most similar (default: 1, the reference image)")
    p.add_argument("--reference-mode", default="retrieval", choices=("retrieval", "triangulation"),
                   help="with --references K >= 2: 'triangulation' = the paper's depth-free baseline "
                        "(relative directions to the two most similar references; default: retrieval)")
    p.add_argument("--track", default="single", choices=("single", "multi"),
                   help="'multi': the multi-frame track — relocalize each scored query's 9-frame burst, fuse "
                        "them through poses_device.txt (derived from ground truth with simulated drift when a "
                        "scene has none); per-frame results go to OUTPUT.frames.zip (default: single)")
    p.add_argument("--resume", action="store_true", help="continue the run journaled beside OUTPUT")
    p.add_argument("--overwrite", action="store_true", help="discard an existing journal and start again")
    p.add_argument("--scenes", help="comma-separated scene names (default: all)")
    p.add_argument("--confidence", help="extra score to use as the submission confidence "
                                        "(e.g. confidence_inliers, confidence_score)")
    p.add_argument("--checkpoint", type=Path, default=None,
                   help="trained checkpoint for a regression method (e.g. --method rpr --checkpoint best.ckpt)")
    p.add_argument("--evaluate", action="store_true", help="score the submission against the split's poses")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--list-methods", action="store_true", help="print the method names (with what each runs and needs) and exit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..data import FormatError
    from ..methods import describe_methods

    if args.list_methods:
        print("\n".join(f"{name:42s} {what}".rstrip() for name, what in describe_methods()))
        return 0
    if args.root is None or not args.method:
        print("mapfree run: error: ROOT and --method are required (or --list-methods)", file=sys.stderr)
        return 2
    if args.workers < 1:
        print("mapfree run: error: --workers must be >= 1", file=sys.stderr)
        return 2
    if args.batch is not None and args.batch < 0:
        print("mapfree run: error: --batch must be >= 0", file=sys.stderr)
        return 2
    if args.track == "multi" and args.all_frames:
        print("mapfree run: error: --all-frames cannot be combined with --track multi (the multi-frame track "
              "runs the 9-frame bursts of the scored queries)", file=sys.stderr)
        return 2
    from ..relocalize import run_split

    try:
        method = args.method
        if getattr(args, "checkpoint", None) is not None:
            method = _with_checkpoint(method, args.checkpoint)
        if args.references != 1 or args.reference_mode != "retrieval":
            from ..relocalize.references import with_references

            method = with_references(method, args.references, args.reference_mode)
        run = run_split
        if args.track == "multi":
            from ..relocalize.multiframe import run_multi as run
        res = run(args.root, args.split, method, args.output, workers=args.workers,
                  all_frames=args.all_frames, resume=args.resume, overwrite=args.overwrite,
                  confidence=args.confidence, progress=not args.no_progress,
                  scenes=args.scenes.split(",") if args.scenes else None, batch_size=args.batch)
    except (FileExistsError, FileNotFoundError, FormatError, KeyError, ValueError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        print(f"mapfree run: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        from ..relocalize import journal_path, read_journal
        from ..relocalize.multiframe import frames_path

        jpath = journal_path(frames_path(args.output) if args.track == "multi" else args.output)
        print(f"mapfree run: interrupted; the {len(read_journal(jpath)[1])} finished frames are kept in {jpath}: "
              f"run the same command with --resume to continue", file=sys.stderr)
        return 130
    out = res.to_dict()
    error = None
    if args.evaluate:
        from ..benchmark import EvaluationError, evaluate

        try:
            out["metrics"] = evaluate(res.submission, args.root, args.split, track=args.track).metrics
        except (EvaluationError, FormatError, FileNotFoundError, ValueError) as e:
            error = (f"mapfree run: error: the submission {res.submission} was written but cannot be scored here: "
                     f"{e}; score it with `mapfree evaluate {res.submission} --dataset {args.root} --split "
                     f"{args.split} --gt-root GT` when you hold the ground truth")
    print(json.dumps(out, indent=2, allow_nan=False))
    if error:
        print(error, file=sys.stderr)
        return 2
    return 0


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

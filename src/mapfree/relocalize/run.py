"""Relocalize a whole split into a submission: parallel over scenes, resumable, with a failure log.

Every finished frame is appended at once to a JSON-lines journal beside the output
(``submission.journal.jsonl``), so a killed run loses nothing: ``resume=True`` skips the frames already
there. The submission ZIP and the failure log (``submission.failures.jsonl``) are rebuilt from the journal.

``run_split`` in steps: check the inputs and the journal (``_plan``, ``_check_method``), start the journal
(``_start_journal``; its records are ``journal.py``'s), compute the frames here, in a process pool or on Ray
(``_dispatch``; ``distributed.py``), write the submission from the whole journal (``_result``).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ..benchmark import write_submission
from ..calibration import Calibration, calibration_for
from ..data import Dataset, Scene
from ..methods import CASCADE, Method, depth_free_problem, get
from .journal import (
    Failure,
    FrameRecord,
    Journal,
    JournalHeader,
    append_records,
    check_resumable,
    drop_stale,
    estimate_scores,
    failures_path,
    journal_path,
    positive,
    read_journal,
    rewrite_journal,
    scene_fingerprint,
    write_failures,
    write_header,
)
from .preflight import CALIBRATED, check_confidence, check_depth_files, check_output, pick_scenes, selection_of
from .references import check_scene_references
from .scenes import (
    check_available,
    check_depth_source,
    open_scene,
    save_figure,
    scene_results,
    set_up_worker,
    sigint_ignored,
    write_frame_figure,
)

__all__ = [
    "RunResult",
    "run_split",
    "journal_path",
    "failures_path",
    "read_journal",
    "frames_to_run",
    "estimate_scores",
    "scene_fingerprint",
    "check_available",
    "check_depth_source",
    "write_frame_figure",
]

# Set in pool workers: the parent's request to stop after the frame in flight (Ctrl-C, an error elsewhere).
_STOP: Any = None


@dataclass
class RunResult:
    """What a run did: paths it wrote and frame counts (``computed`` this time, ``skipped`` from the journal)."""

    submission: Path
    journal: Path
    failures: Path
    computed: int = 0
    skipped: int = 0
    estimated: int = 0
    failed: int = 0
    seconds: float = 0.0
    scenes: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    stale_scenes: list[str] = field(default_factory=list)  # resumed scenes whose data changed: recomputed
    torn_lines: int = 0  # resumed journal's lines cut mid-write (a kill, a full disk): dropped, their frames redone
    cluster: dict[str, Any] = field(default_factory=dict)  # --ray: address, nodes, workers, frames handed out again

    def to_dict(self) -> dict[str, Any]:
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in self.__dict__.items()}


# --------------------------------------------------------------------------- work


def frames_to_run(scene: Scene, all_frames: bool) -> list[str]:
    """The query frames of a scene: the benchmark's scored ones, or every query."""
    frames = scene.queries if all_frames else scene.scored_queries()
    return [f.name for f in frames]


def _run_scene(
    method: Method,
    scene_path: str,
    frames: list[str],
    journal: str,
    on_frame: Callable[[FrameRecord], None] | None = None,
    batch_size: int | None = None,
    viz_dir: str | None = None,
) -> int:
    """Relocalize ``frames`` of one scene against its reference, appending each result to the journal."""
    if _stopping():  # a scene already handed to this worker when the parent asked to stop: not started
        return 0
    journal_p = Path(journal)
    ref = open_scene(method, scene_path)
    for res in scene_results(ref, method, frames, batch_size, figures=viz_dir is not None):
        append_records(journal_p, [res.record])
        save_figure(viz_dir, res)
        on_frame and on_frame(res.record)
        if _stopping() and ref.localizer is not None:  # asked to stop: the frame in flight is journaled, no more
            break
    return len(frames)


def _stopping() -> bool:
    """Whether the parent asked this pool worker to stop (never in the parent's own process)."""
    return _STOP is not None and _STOP.is_set()


def _init_worker(threads: int, stop: Any = None) -> None:
    """Pool worker set-up (``set_up_worker``: ``threads`` per library, the heap kept warm), and Ctrl-C left to the
    parent, which sets ``stop``."""
    global _STOP
    _STOP = stop
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    set_up_worker(threads)


# --------------------------------------------------------------------------- validate


@dataclass
class _Plan:
    """A run once its inputs are checked: the journal it keeps, the scenes and the frames still to compute."""

    method: Method
    output: Path
    journal_path: Path
    journal: Journal  # as read; its frames are those kept (none for a fresh run)
    header: JournalHeader  # the header this run writes
    fresh: bool  # the journal is started again
    scenes: list[Scene]
    stale: list[str]
    todo: list[tuple[Scene, list[str]]]

    @property
    def total(self) -> int:
        """Frames to compute."""
        return sum(len(f) for _, f in self.todo)

    @property
    def skipped(self) -> int:
        """Frames kept from the journal."""
        return len(self.journal.done())


def _plan(
    root: os.PathLike | str,
    split: str,
    m: Method,
    output: Path,
    *,
    all_frames: bool,
    resume: bool,
    overwrite: bool,
    confidence: str | None,
    scenes: Sequence[str] | None,
    select: Callable[[Scene], list[str]] | None,
) -> _Plan:
    """Check the output, the confidence and the journal beside the output; then the scenes and the frames to run
    (the journal's kept, its stale scenes' dropped)."""
    check_output(output)
    check_confidence(confidence, m)
    jpath = journal_path(output)
    journal = Journal.read(jpath)
    selection = selection_of(all_frames, select)
    fresh = check_resumable(jpath, journal, m.to_dict(), selection, resume, overwrite)
    if fresh:
        journal.frames = []
    scene_list = Dataset(root).scenes(split)
    if not scene_list:
        raise ValueError(f"the {split} split holds no scenes: {Path(root) / split} has no sNNNNN folder")
    if scenes:
        scene_list = pick_scenes(scene_list, scenes, split)
    fingerprints = {s.name: scene_fingerprint(s.path) for s in scene_list}
    stale = [] if fresh else drop_stale(journal, fingerprints)
    done = journal.done()
    todo: list[tuple[Scene, list[str]]] = []
    for s in scene_list:
        wanted_frames = select(s) if select is not None else frames_to_run(s, all_frames)
        names = [f for f in wanted_frames if (s.name, f) not in done]
        if names:
            todo.append((s, names))
    if fresh or journal.header is None:
        header = JournalHeader(m.to_dict(), str(root), split, all_frames, selection, fingerprints)
    else:
        header = replace(journal.header, data={**journal.header.data, **fingerprints})
    return _Plan(m, output, jpath, journal, header, fresh, scene_list, stale, todo)


def _check_method(plan: _Plan, split: str, build_here: bool, keep: bool) -> None:
    """Refuse a method that cannot run on these scenes (no depth to work from, depth files that are not there,
    references it cannot bind); with ``build_here``, build it and check its networks load (``keep``: this
    process computes the frames itself)."""
    m = plan.method
    problem = depth_free_problem(m)
    if problem:  # a split's frames come without depth maps of their own: nothing could succeed
        raise ValueError(problem)
    check_depth_files(m, plan.scenes, split)
    check_scene_references(plan.scenes, m)
    if plan.todo and build_here:
        check_available(m, keep=keep)


# --------------------------------------------------------------------------- journal


def _start_journal(plan: _Plan) -> None:
    """Write the journal's header (a fresh run), or rewrite the journal with the records read back whole (a
    torn last line goes with the rewrite). Only once the inputs were checked: bad data refused before leaves an
    existing journal (--overwrite too) as it was."""
    if plan.fresh or plan.journal.header is None:
        write_header(plan.journal_path, plan.header)
    else:
        rewrite_journal(plan.journal_path, plan.header, plan.journal.frames)


# --------------------------------------------------------------------------- dispatch


def _dispatch(
    plan: _Plan,
    bar: Any,
    *,
    workers: int,
    batch_size: int | None,
    viz_dir: str | None,
    ray: tuple[str, Any, os.PathLike | str, str] | None,
) -> dict[str, Any]:
    """Compute the plan's frames: on a Ray cluster (``ray``: address, ``RayOptions``, root, split), in a pool of
    ``workers`` processes, or here, one scene after the other. Returns what the cluster did (``{}`` locally)."""
    m, todo, jpath = plan.method, plan.todo, plan.journal_path
    if ray is not None and todo:
        from .distributed import RayOptions, run_on_ray

        address, options, root, split = ray
        work = [(os.path.abspath(s.path), names) for s, names in todo]  # workers do not share our cwd
        run = run_on_ray(
            m, work, jpath, bar, address, options or RayOptions(), os.path.abspath(root), split, batch_size, viz_dir
        )
        return run.to_dict()
    if workers <= 1 or len(todo) <= 1:
        for s, names in todo:
            _run_scene(m, str(s.path), names, str(jpath), lambda r: bar.update(1), batch_size, viz_dir)
    else:
        _run_parallel(m, todo, jpath, workers, bar, batch_size, viz_dir)
    return {}


# --------------------------------------------------------------------------- write


def _submitted(r: FrameRecord, confidence: str | None, calibration: Calibration | None) -> float:
    """A frame's submission confidence: ``calibrated`` from its signals (a calibration given on --resume applies
    to all), else the score ``confidence`` names, else the method's own."""
    if confidence != CALIBRATED:
        return r.score(confidence)
    if calibration is not None:
        return positive(calibration.p_correct(r.signals, r.confidence))
    return positive(r.p_correct if r.p_correct is not None else 0.0)


def _write_outputs(
    output: Path,
    scenes: list[str],
    recs: list[FrameRecord],
    confidence: str | None,
    calibration: Calibration | None = None,
) -> tuple[int, int]:
    """Write the submission ZIP and its failure log from the journal's records; (estimated, failed) frames."""
    by_scene: dict[str, list] = {s: [] for s in scenes}
    failures = []
    # Frame order, not journal order (which is the order workers finished in): the same ZIP wherever they ran.
    for r in sorted(recs, key=lambda r: r.key):
        if r.scene not in by_scene:
            continue
        if r.ok:
            by_scene[r.scene].append((r.frame, r.world_pose(), _submitted(r, confidence, calibration)))
        else:
            failures.append(Failure(r.scene, r.frame, r.reason))
    write_submission(output, by_scene)
    write_failures(output, failures)
    return sum(len(v) for v in by_scene.values()), len(failures)


def _result(plan: _Plan, confidence: str | None, cluster: dict[str, Any], seconds: float) -> RunResult:
    """Write the outputs from the whole journal (this run's frames and the kept ones) and say what was done."""
    m = plan.method
    recs = Journal.read(plan.journal_path).frames
    calibration = calibration_for(m.name, m.options) if confidence == CALIBRATED and m.kind != CASCADE else None
    estimated, failed = _write_outputs(plan.output, [s.name for s in plan.scenes], recs, confidence, calibration)
    timing_sums: dict[str, float] = {}
    for r in recs:
        for k, v in r.timings.items():
            timing_sums[k] = timing_sums.get(k, 0.0) + v
    return RunResult(
        plan.output,
        plan.journal_path,
        failures_path(plan.output),
        computed=plan.total,
        skipped=plan.skipped,
        estimated=estimated,
        failed=failed,
        seconds=seconds,
        scenes=len(plan.scenes),
        timings=timing_sums,
        stale_scenes=plan.stale,
        torn_lines=0 if plan.fresh else plan.journal.torn,
        cluster=cluster,
    )


def run_split(
    root: os.PathLike | str,
    split: str,
    method: Any,
    output: os.PathLike | str,
    *,
    workers: int = 1,
    all_frames: bool = False,
    resume: bool = False,
    overwrite: bool = False,
    confidence: str | None = None,
    scenes: Sequence[str] | None = None,
    progress: bool = True,
    select: Callable[[Scene], list[str]] | None = None,
    batch_size: int | None = None,
    viz_dir: os.PathLike | str | None = None,
    ray_address: str | None = None,
    ray_options: Any = None,
) -> RunResult:
    """Relocalize every (scored) query of ``split`` and write a submission ZIP at ``output``.

    ``method``: a name, YAML path or ``Method``. ``confidence``: a key of the solver's extra scores to use
    as the submission confidence instead of the method's own. With ``resume`` the journal's frames are kept.
    ``select`` (optional) names the frames to run in a scene instead (the multi-frame track's bursts).
    ``batch_size``: queries per device pass of the batched pipeline (0: one pair at a time; ``None``: 16 when
    the matcher runs on a GPU, else 0). ``viz_dir``: draw each frame computed by this call there
    (``frame_figure_path``: matches + AR check).

    ``ray_address``: compute the frames on a Ray cluster instead of ``workers`` local processes (``"local"``
    starts Ray on this machine; ``"auto"``, ``HOST:PORT`` or ``ray://HOST:PORT`` joins a running cluster), with
    the resources per worker of ``ray_options`` (a ``distributed.RayOptions``); this process keeps the journal,
    and the results are the same as a local run's (``mapfree.relocalize.distributed``).
    """
    t_start = time.perf_counter()
    m = method if isinstance(method, Method) else get(method)
    plan = _plan(
        root,
        split,
        m,
        Path(output),
        all_frames=all_frames,
        resume=resume,
        overwrite=overwrite,
        confidence=confidence,
        scenes=scenes,
        select=select,
    )
    # on a cluster, every worker checks the method on its own node
    _check_method(plan, split, build_here=ray_address is None, keep=workers <= 1 or len(plan.todo) <= 1)
    _start_journal(plan)
    bar = _progress(plan.total, plan.skipped, progress, m.name)
    ray = None if ray_address is None else (ray_address, ray_options, root, split)
    viz = str(viz_dir) if viz_dir is not None else None
    try:
        cluster = _dispatch(plan, bar, workers=workers, batch_size=batch_size, viz_dir=viz, ray=ray)
    finally:
        bar.close()
    return _result(plan, confidence, cluster, time.perf_counter() - t_start)


def _run_parallel(
    m: Method,
    todo: list[tuple[Scene, list[str]]],
    jpath: Path,
    workers: int,
    bar: Any,
    batch_size: int | None = None,
    viz_dir: str | None = None,
) -> None:
    threads = max(1, (os.cpu_count() or 1) // workers)
    offset = jpath.stat().st_size
    ctx = mp.get_context("spawn")  # torch and OpenCV threads do not survive fork reliably
    stop = ctx.Event()
    with ProcessPoolExecutor(
        max_workers=min(workers, len(todo)), mp_context=ctx, initializer=_init_worker, initargs=(threads, stop)
    ) as pool:
        # Largest scenes first so that the last worker to finish is not left with a big one. The workers are
        # spawned here, while Ctrl-C is ignored: they inherit that, so one pressed while a worker still imports
        # (seconds, before ``_init_worker``) no longer prints a KeyboardInterrupt traceback from it.
        with sigint_ignored():
            futures = [
                pool.submit(_run_scene, m, str(s.path), names, str(jpath), None, batch_size, viz_dir)
                for s, names in sorted(todo, key=lambda x: -len(x[1]))
            ]
        pending = set(futures)
        try:
            while pending:
                finished, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                with open(jpath, "rb") as f:  # progress = new complete lines in the journal
                    f.seek(offset)
                    chunk = f.read()
                n = chunk.rfind(b"\n") + 1
                bar.update(chunk[:n].count(b"\n"))
                offset += n
                for fut in finished:
                    fut.result()  # re-raise a worker crash
        except BaseException:
            # Ctrl-C or a crash: queued scenes never start, running ones stop after their frame in flight
            # (journaled), so leaving the pool takes a frame, not the rest of the split. A second Ctrl-C
            # meanwhile would break the pool's shutdown and hang the exit on its idle workers: it waits.
            stop.set()
            for fut in pending:
                fut.cancel()
            with sigint_ignored():
                pool.shutdown(wait=True)
            raise


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        pass

    def write(self, s: str) -> None:
        print(s, file=sys.stderr)

    def close(self) -> None:
        pass


def _progress(total: int, initial: int, enabled: bool, desc: str) -> Any:
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total + initial, initial=initial, desc=desc, unit="frame", dynamic_ncols=True)

"""Relocalize a whole split into a submission: parallel over scenes, resumable, with a failure log.

Every finished frame is appended at once to a JSON-lines journal beside the output
(``submission.journal.jsonl``), so a killed run loses nothing: ``resume=True`` skips the frames already
there. The submission ZIP and the failure log (``submission.failures.jsonl``) are rebuilt from the journal.
"""

from __future__ import annotations

import hashlib
import json
import logging
import multiprocessing as mp
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..benchmark import write_submission
from ..calibration import CALIBRATION_OPTION, Calibration, calibration_for
from ..data import REFERENCE_NAME, Dataset, Scene
from ..data.io import depth_suffixes, naming
from ..geometry import Pose
from ..methods import CASCADE, Method, depth_free_problem, get
from .preflight import CALIBRATED, check_confidence, check_output, check_same_selection, selection_of
from .references import check_scene_references
from .scenes import (
    append_records,
    check_available,
    check_depth_source,
    estimate_scores,
    open_scene,
    save_figure,
    scene_results,
    set_threads,
    sigint_ignored,
    write_frame_figure,
)

log = logging.getLogger(__name__)

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

JOURNAL_VERSION = 1

# Set in pool workers: the parent's request to stop after the frame in flight (Ctrl-C, an error elsewhere).
_STOP: Any = None


def journal_path(output: os.PathLike | str) -> Path:
    """``out/submission.zip`` -> ``out/submission.journal.jsonl``."""
    p = Path(output)
    return p.with_name(f"{p.stem}.journal.jsonl")


def failures_path(output: os.PathLike | str) -> Path:
    p = Path(output)
    return p.with_name(f"{p.stem}.failures.jsonl")


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


# --------------------------------------------------------------------------- journal


def read_journal(path: os.PathLike | str) -> tuple[dict | None, list[dict]]:
    """(header, frame records) of a journal; a torn line (killed mid-write, a full disk) is left out
    (a resumed run counts them in ``RunResult.torn_lines``)."""
    header, recs, _ = _read_journal(Path(path))
    return header, recs


def _read_journal(path: Path) -> tuple[dict | None, list[dict], int]:
    """(header, frame records, lines that are not a whole record) of a journal."""
    if not path.is_file():
        return None, [], 0
    header, recs, torn = None, [], 0
    for line in path.read_text(errors="replace").splitlines():
        try:
            r = json.loads(line)
        except json.JSONDecodeError:
            torn += bool(line.strip())
            continue
        if not isinstance(r, dict):
            torn += 1
        elif r.get("kind") == "header":
            header = header or r
        elif r.get("kind") == "frame":
            recs.append(r)
    return header, recs, torn


def scene_fingerprint(scene_dir: os.PathLike | str) -> str:
    """What a scene's data looked like: a hash of its text files' bytes and of every other file's name, size and
    modification time (images and depth maps are not read). A resumed run recomputes a scene whose print changed."""
    h = hashlib.sha1()
    root = Path(scene_dir)
    for p in sorted(root.rglob("*")):
        if not p.is_file():
            continue
        rel = p.relative_to(root).as_posix()
        if p.suffix == ".txt":
            h.update(f"{rel}\0".encode() + p.read_bytes() + b"\0")
        else:
            st = p.stat()
            h.update(f"{rel}\0{st.st_size}\0{st.st_mtime_ns}\0".encode())
    return h.hexdigest()


def _drop_stale(header: dict | None, recs: list[dict], fingerprints: dict[str, str]) -> tuple[list[dict], list[str]]:
    """Journal records of scenes whose data is unchanged since they were computed, and the names of those that
    changed (or have no recorded print: a journal of an older version), whose records are dropped (the run's
    ``stale_scenes``: the CLI says so)."""
    known = (header or {}).get("data", {})
    stale = sorted(
        {r["scene"] for r in recs if r["scene"] in fingerprints and known.get(r["scene"]) != fingerprints[r["scene"]]}
    )
    return [r for r in recs if r["scene"] not in stale], stale


def _rewrite_journal(jpath: Path, header: dict, recs: list[dict]) -> None:
    """Replace the journal by ``header`` + ``recs`` (atomically: a kill meanwhile leaves the old one)."""
    tmp = jpath.with_name(jpath.name + ".tmp")
    with naming(jpath):
        tmp.write_text("".join(json.dumps(r, allow_nan=False) + "\n" for r in [header, *recs]))
    os.replace(tmp, jpath)


def _same_method(a: dict, b: dict) -> bool:
    """Whether two journal headers' methods give the same estimates (a calibration file only sets ``p_correct``,
    recomputed from the journal's signals when the submission is written)."""
    keys = ("kind", "matcher", "matcher_opts", "depth", "solver", "solver_opts")
    options = [{k: v for k, v in (m.get("options") or {}).items() if k != CALIBRATION_OPTION} for m in (a, b)]
    return all(a.get(k) == b.get(k) for k in keys) and options[0] == options[1]


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
    on_frame: Callable[[dict], None] | None = None,
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
    """Pool worker set-up: ``threads`` per library, and Ctrl-C left to the parent, which sets ``stop``."""
    global _STOP
    _STOP = stop
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    set_threads(threads)


# --------------------------------------------------------------------------- outputs


def _write_outputs(
    output: Path, scenes: list[str], recs: list[dict], confidence: str | None, calibration: Calibration | None = None
) -> tuple[int, int]:
    by_scene: dict[str, list] = {s: [] for s in scenes}
    failures = []
    # Frame order, not journal order (which is the order workers finished in): the same ZIP wherever they ran.
    for r in sorted(recs, key=lambda r: (r["scene"], r["frame"])):
        if r["scene"] not in by_scene:
            continue
        if r["ok"]:
            if confidence == CALIBRATED:  # from the signals: a calibration given on --resume applies to all
                conf = calibration.p_correct(r["signals"], r["confidence"]) if calibration else r.get("p_correct", 0.0)
            else:
                conf = r["scores"].get(confidence, r["confidence"]) if confidence else r["confidence"]
            conf = float(conf) if np.isfinite(conf) and conf > 0 else 0.0
            by_scene[r["scene"]].append((r["frame"], Pose.from_qt(r["q"], r["t"]), conf))
        else:
            failures.append({"scene": r["scene"], "frame": r["frame"], "reason": r["reason"]})
    write_submission(output, by_scene)
    fp = failures_path(output)
    with naming(fp):
        fp.write_text("".join(json.dumps(f) + "\n" for f in failures))
    return sum(len(v) for v in by_scene.values()), len(failures)


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
    output = Path(output)
    check_output(output)
    check_confidence(confidence, m)
    jpath = journal_path(output)
    header, recs, torn = _read_journal(jpath)
    if recs and not resume and not overwrite:
        raise FileExistsError(
            f"{jpath} already holds {len(recs)} results: run again with --resume to continue "
            f"that run or --overwrite to start again (in Python: resume=True, overwrite=True)"
        )
    selection = selection_of(all_frames, select)
    if resume and header is not None and not overwrite:
        if not _same_method(header["method"], m.to_dict()):
            raise ValueError(
                f"{jpath} was written by method {header['method'].get('name')!r}, not {m.name!r}: "
                f"use another output path or --overwrite"
            )
        check_same_selection(jpath, header, selection)
    fresh = overwrite or not resume or header is None
    if fresh:
        recs = []

    ds = Dataset(root)
    scene_list = ds.scenes(split)
    if not scene_list:
        raise ValueError(f"the {split} split holds no scenes: {Path(root) / split} has no sNNNNN folder")
    if scenes:
        scene_list = _pick_scenes(scene_list, scenes, split)
    fingerprints = {s.name: scene_fingerprint(s.path) for s in scene_list}
    stale: list[str] = []
    if not fresh:
        recs, stale = _drop_stale(header, recs, fingerprints)
    done = {(r["scene"], r["frame"]) for r in recs}
    todo: list[tuple[Scene, list[str]]] = []
    for s in scene_list:
        wanted_frames = select(s) if select is not None else frames_to_run(s, all_frames)
        names = [f for f in wanted_frames if (s.name, f) not in done]
        if names:
            todo.append((s, names))

    problem = depth_free_problem(m)
    if problem:  # a split's frames come without depth maps of their own: nothing could succeed
        raise ValueError(problem)
    _check_depth_files(m, scene_list, split)
    check_scene_references(scene_list, m)
    if todo and ray_address is None:  # on a cluster, every worker checks the method on its own node
        check_available(m, keep=workers <= 1 or len(todo) <= 1)
    # The journal is (re)started only now: bad data refused above leaves an existing one (--overwrite too) as it was.
    if fresh or header is None:
        with naming(jpath):
            jpath.write_text(
                json.dumps(
                    {
                        "kind": "header",
                        "version": JOURNAL_VERSION,
                        "method": m.to_dict(),
                        "root": str(root),
                        "split": split,
                        "all_frames": all_frames,
                        "frames": selection,
                        "data": fingerprints,
                    }
                )
                + "\n"
            )
    else:  # the records read back whole: a torn last line goes with the rewrite
        _rewrite_journal(jpath, {**header, "data": {**header.get("data", {}), **fingerprints}}, recs)
    total = sum(len(f) for _, f in todo)
    bar = _progress(total, len(done), progress, m.name)
    viz = str(viz_dir) if viz_dir is not None else None
    cluster: dict[str, Any] = {}
    try:
        if ray_address is not None and todo:
            from .distributed import RayOptions, run_on_ray

            work = [(os.path.abspath(s.path), names) for s, names in todo]  # workers do not share our cwd
            cluster = run_on_ray(
                m,
                work,
                jpath,
                bar,
                ray_address,
                ray_options or RayOptions(),
                os.path.abspath(root),
                split,
                batch_size,
                viz,
            ).to_dict()
        elif workers <= 1 or len(todo) <= 1:
            for s, names in todo:
                _run_scene(
                    m,
                    str(s.path),
                    names,
                    str(jpath),
                    on_frame=lambda r: bar.update(1),
                    batch_size=batch_size,
                    viz_dir=viz,
                )
        else:
            _run_parallel(m, todo, jpath, workers, bar, batch_size, viz)
    finally:
        bar.close()
    _, recs = read_journal(jpath)
    calibration = calibration_for(m.name, m.options) if confidence == CALIBRATED and m.kind != CASCADE else None
    estimated, failed = _write_outputs(output, [s.name for s in scene_list], recs, confidence, calibration)
    timing_sums: dict[str, float] = {}
    for r in recs:
        for k, v in r.get("timings", {}).items():
            timing_sums[k] = timing_sums.get(k, 0.0) + v
    return RunResult(
        output,
        jpath,
        failures_path(output),
        computed=total,
        skipped=len(done),
        estimated=estimated,
        failed=failed,
        seconds=time.perf_counter() - t_start,
        scenes=len(scene_list),
        timings=timing_sums,
        stale_scenes=stale,
        torn_lines=0 if fresh else torn,
        cluster=cluster,
    )


def _pick_scenes(scene_list: list[Scene], names: Sequence[str], split: str) -> list[Scene]:
    """The scenes named, in split order; a name the split does not hold is refused (with the nearest ones)."""
    import difflib

    have = [s.name for s in scene_list]
    unknown = [n for n in dict.fromkeys(names) if n not in have]
    if unknown:
        hints = []
        for n in unknown:
            close = difflib.get_close_matches(n, have, n=2, cutoff=0.6)
            hints.append(f"{n} (did you mean {' or '.join(close)}?)" if close else n)
        raise ValueError(
            f"the {split} split has no scene {', '.join(hints)}; it holds {len(have)} scene(s)"
            + (f": {', '.join(have[:8])}{' …' if len(have) > 8 else ''}" if have else "")
        )
    wanted = set(names)
    return [s for s in scene_list if s.name in wanted]


def _check_depth_files(m: Method, scene_list: list[Scene], split: str) -> None:
    """A ``files:SUFFIX`` method whose depth maps exist at no scene's reference is a typo in the suffix (or the
    wrong split), not a run of failures: refuse it before any work, naming the suffixes that do exist."""
    if m.kind != "matching" or not m.depth.startswith("files:") or not scene_list:
        return
    suffix = m.depth.split(":", 1)[1]
    refs = [s.frames[REFERENCE_NAME] for s in scene_list if REFERENCE_NAME in s.frames]
    if not refs or any(f.has_depth(suffix) for f in refs):
        return
    found = sorted({s for f in refs for s in depth_suffixes(f.image_path)})
    raise ValueError(
        f"method {m.name!r} reads depth maps *.{suffix}.png, but no reference image of the {split} "
        f"split has one (e.g. {refs[0].depth_path(suffix)}); depth suffixes there: "
        f"{', '.join(found) or 'none'} (pick one with NAME@SUFFIX or the method's last part)"
    )


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

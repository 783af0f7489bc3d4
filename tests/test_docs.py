"""The documentation's examples run as written.

Every ```bash and ```python block of the tutorials (docs/tutorials/*.md) and of getting started runs, in page
order, in a fresh folder: shell blocks with ``bash -euo pipefail``, Python blocks in one shared namespace, so a
page reads top to bottom like a session. A block that must not run is preceded by
``<!-- docs-test: skip (why) -->``; the reason is required. The README's Python example runs on the data
``mapfree demo`` writes. The pages that take a minute or more are ``slow``.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
TUTORIALS = sorted((DOCS / "tutorials").glob("*.md"))
SLOW_PAGES = {"training-rpr.md", "phone-scans.md", "serving.md", "k-references.md"}
SKIP = re.compile(r"<!--\s*docs-test:\s*skip\s*\((?P<why>[^)]+)\)\s*-->")
FENCE = re.compile(r"^(?P<indent>\s*)```(?P<lang>[\w-]*)\s*$")
# The serving tutorial's port; each run takes a free one instead, so parallel runs cannot collide.
TUTORIAL_PORT = "8765"


@dataclass
class Block:
    lang: str
    code: str
    line: int  # 1-based line of the opening fence
    skip: str | None = None  # the reason, when marked


def blocks(text: str) -> list[Block]:
    """The fenced blocks of a Markdown page, with their language, first line and skip marker."""
    out: list[Block] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m or not m["lang"]:
            i += 1
            continue
        start, indent = i, len(m["indent"])
        body = []
        i += 1
        while i < len(lines) and not FENCE.match(lines[i]):
            body.append(lines[i][indent:])
            i += 1
        prev = next((lines[k] for k in range(start - 1, -1, -1) if lines[k].strip()), "")
        marker = SKIP.search(prev)
        out.append(Block(m["lang"], "\n".join(body) + "\n", start + 1, marker["why"] if marker else None))
        i += 1
    return out


def runnable(path: Path) -> list[Block]:
    return [b for b in blocks(path.read_text()) if b.lang in ("bash", "python") and b.skip is None]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


DRIVER = textwrap.dedent("""
    import json, subprocess, sys, traceback
    blocks = json.load(open(sys.argv[1]))
    ns = {"__name__": "__main__"}
    for b in blocks:
        print(f"--- {b['where']} ({b['lang']})", flush=True)
        if b["lang"] == "bash":
            rc = subprocess.run(["bash", "-euo", "pipefail", "-c", b["code"]]).returncode
            if rc:
                sys.exit(f"FAILED {b['where']}: exit status {rc}")
        else:
            try:
                exec(compile(b["code"], b["where"], "exec"), ns)
            except BaseException:
                traceback.print_exc()
                sys.exit(f"FAILED {b['where']}")
""")


def run_page(blocks_: list[Block], page: str, cwd: Path, timeout: float, replace: dict[str, str] | None = None) -> str:
    """Run ``blocks_`` in order in ``cwd`` (one driver process, its own process group) and return the output."""
    import json

    payload = []
    for b in blocks_:
        code = b.code
        for old, new in (replace or {}).items():
            code = code.replace(old, new)
        payload.append({"lang": b.lang, "code": code, "where": f"{page}:{b.line}"})
    (cwd / ".blocks.json").write_text(json.dumps(payload))
    (cwd / ".driver.py").write_text(DRIVER)
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"  # mapfree, python of this venv
    env["PYTHONPATH"] = f"{ROOT / 'src'}{os.pathsep}{env.get('PYTHONPATH', '')}".rstrip(os.pathsep)
    env.setdefault("MPLBACKEND", "Agg")
    proc = subprocess.Popen(
        [sys.executable, ".driver.py", ".blocks.json"],
        cwd=cwd,
        env=env,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        out = ""
        proc.returncode = -1
    finally:
        # whatever a block left running (the serving tutorial's server and its workers) ends with the page
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    if proc.returncode:
        pytest.fail(f"{page}: a documented block failed\n{out[-6000:]}", pytrace=False)
    return out


def test_block_parser_reads_fences_languages_lines_and_skip_markers():
    text = (
        "# t\n\n```bash\necho a\n```\n\n<!-- docs-test: skip (installs packages) -->\n```bash\npip x\n```\n"
        "- item:\n  ```python\n  print(1)\n  ```\n```text\nnot code\n```\n"
    )
    got = blocks(text)
    assert [(b.lang, b.line, b.skip) for b in got] == [
        ("bash", 3, None),
        ("bash", 8, "installs packages"),
        ("python", 12, None),
        ("text", 15, None),
    ]
    assert got[2].code == "print(1)\n"


# The pages that train, build, serve or describe images with DenseVLAD take a minute or more on a shared CPU.
PAGES = [pytest.param(p, id=p.name, marks=[pytest.mark.slow] if p.name in SLOW_PAGES else []) for p in TUTORIALS]


@pytest.mark.slow
@pytest.mark.parametrize("path", PAGES)
def test_tutorial_blocks_run(path: Path, tmp_path: Path):
    todo = runnable(path)
    if path.name == "index.md":
        assert not todo
        return
    assert todo, f"{path.name} has no runnable block"
    skipped = [b.line for b in blocks(path.read_text()) if b.lang in ("bash", "python") and b.skip]
    assert not skipped, f"{path.name}: tutorials run every block; skipped at lines {skipped}"
    if path.name == "serving.md" and shutil.which("curl") is None:
        pytest.skip("the serving tutorial talks to the server with curl, which this machine lacks")
    port = str(free_port())
    out = run_page(todo, f"docs/tutorials/{path.name}", tmp_path, timeout=540, replace={TUTORIAL_PORT: port})
    assert out.count("--- docs/tutorials/") == len(todo)


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory) -> Path:
    """A folder holding ``demo-out/`` as ``mapfree demo`` writes it (one scene, enough queries for the pages)."""
    d = tmp_path_factory.mktemp("demo")
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    r = subprocess.run(
        [sys.executable, "-m", "mapfree", "demo", "--out", "demo-out", "--scenes", "1", "--queries", "25"],
        cwd=d,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert (d / "demo-out" / "submission.zip").is_file()
    return d


@pytest.mark.slow
def test_getting_started_blocks_run_after_the_demo(demo_dir: Path):
    page = DOCS / "getting-started.md"
    marked = [b for b in blocks(page.read_text()) if b.skip]
    assert all(b.skip.strip() for b in marked)  # every skipped block says why
    run_page(runnable(page), "docs/getting-started.md", demo_dir, timeout=300)
    assert (demo_dir / "pair.png").stat().st_size > 10_000  # the --viz figure


@pytest.mark.slow
def test_readme_python_example_runs_on_the_demo_output(demo_dir: Path):
    readme = ROOT / "README.md"
    py = [b for b in blocks(readme.read_text()) if b.lang == "python"]
    assert len(py) == 1 and len(py[0].code.splitlines()) <= 14, "the README keeps one short Python example"
    out = run_page(py, "README.md", demo_dir, timeout=300)
    assert "AUC @ VCRE < 90px" in out  # the score table it prints


def test_readme_is_a_short_front_page_without_outside_references():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    for bad in ("SPEC", "../shared", "the issue", ".gpukit"):
        assert bad not in text, bad
    for link in re.findall(r"\]\(([^)#]+)", text):  # every relative link points into the repository
        if not link.startswith("http"):
            assert (ROOT / link).exists(), link


def test_docs_reference_nothing_outside_the_repository():
    for page in DOCS.rglob("*.md"):
        text = page.read_text()
        for bad in ("SPEC §", "../shared", "the issue", "/work/"):
            assert bad not in text, f"{page.relative_to(ROOT)}: {bad!r}"


def test_api_docstrings_cite_nothing_outside_the_repository():
    """The API reference renders the docstrings: they cite no document a reader of the repository cannot open."""
    for path in (ROOT / "src" / "mapfree").rglob("*.py"):
        text = path.read_text()
        for bad in ("SPEC §", "../shared"):
            assert bad not in text, f"{path.relative_to(ROOT)}: {bad!r}"


def test_cli_reference_has_every_command():
    from mapfree.cli import COMMANDS

    text = (DOCS / "cli.md").read_text()
    missing = [c for c in COMMANDS if not re.search(rf"^###.*`mapfree {c}\b", text, re.M)]
    assert not missing, f"docs/cli.md lacks {missing}"

"""Every row of docs/bad-inputs.md, run as printed in the folder its setup block makes: the exit status it gives and
its one line on stderr (``…`` stands for any text), never a traceback."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "bad-inputs.md"
_ENV = re.compile(r"^[A-Z_][A-Z0-9_]*=")


@dataclass(frozen=True)
class Row:
    what: str
    command: str
    status: int
    line: str  # "—": nothing on stderr


def _cell(text: str) -> str:
    text = text.strip()
    m = re.fullmatch(r"(`+) ?(.*?) ?\1", text)
    return m.group(2) if m else text


def _cells(line: str) -> list[str]:
    """A table line split at its pipes, except those inside code spans (as the Markdown table reads it)."""
    cells, cur, fence, i = [], "", 0, 0
    while i < len(line):
        if line[i] == "`":
            n = len(line[i:]) - len(line[i:].lstrip("`"))
            fence = n if fence == 0 else (0 if n == fence else fence)
            cur += line[i : i + n]
            i += n
            continue
        if line[i] == "|" and fence == 0:
            cells.append(cur)
            cur = ""
        else:
            cur += line[i]
        i += 1
    cells.append(cur)
    return cells


def rows(page: Path = PAGE) -> list[Row]:
    """The table rows of the page: | what | `command` | status | `line` |."""
    out = []
    for ln in page.read_text().splitlines():
        cells = _cells(ln)[1:-1]
        if len(cells) == 4 and "mapfree " in cells[1]:
            out.append(Row(_cell(cells[0]), _cell(cells[1]), int(_cell(cells[2])), _cell(cells[3])))
    return out


def setup_block(page: Path = PAGE) -> str:
    """The page's first bash block: what makes the folder the rows run in."""
    return re.findall(r"```bash\n(.*?)```", page.read_text(), re.S)[0]


def matches(expected: str, line: str) -> bool:
    pattern = ".*".join(re.escape(part) for part in expected.split("…"))
    return re.fullmatch(pattern, line, re.S) is not None


def split_env(command: str) -> tuple[dict[str, str], list[str]]:
    """``VAR=value … mapfree ARGS`` -> ({VAR: value}, ARGS)."""
    words = shlex.split(command)
    env = {}
    while words and _ENV.match(words[0]):
        k, v = words.pop(0).split("=", 1)
        env[k] = v
    assert words[0] == "mapfree", command
    return env, words[1:]


def _tool_env(repo: Path) -> dict[str, str]:
    return {
        **os.environ,
        "PYTHONPATH": str(repo / "src"),
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
    }


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    """The folder of the page's setup block (a small synthetic split, broken files and folders)."""
    repo = PAGE.parents[1]
    d = tmp_path_factory.mktemp("bad-inputs")
    p = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", setup_block()],
        cwd=d,
        env=_tool_env(repo),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    return d


@pytest.fixture
def isolated(workspace, tmp_path, monkeypatch):
    """The rows' folder as working directory, with no weights, caches or network beyond what the rows set."""
    import huggingface_hub.constants as hf

    monkeypatch.chdir(workspace)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # the default weights folder, torch's hub cache
    for var in ("MAPFREE_WEIGHTS_DIR", "TORCH_HOME", "MAPFREE_OFFLINE"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(hf, "HF_HUB_CACHE", str(tmp_path / "hf"))
    return monkeypatch


def run_row(row: Row, monkeypatch, capfd) -> tuple[int, str]:
    """(exit status, stderr) of a row: in this process (``main``), or through bash for a pipeline."""
    if " | " in row.command:
        repo = PAGE.parents[1]
        p = subprocess.run(
            ["bash", "-c", f"{row.command}; exit ${{PIPESTATUS[0]}}"],
            capture_output=True,
            text=True,
            env={**_tool_env(repo), "XDG_CACHE_HOME": os.environ["XDG_CACHE_HOME"]},
            timeout=120,
        )
        return p.returncode, p.stderr
    from mapfree.cli import main

    env, argv = split_env(row.command)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    capfd.readouterr()
    try:
        code = main(argv)
    except SystemExit as e:  # argparse's own refusals
        code = e.code if isinstance(e.code, int) else 1
    return code, capfd.readouterr().err


def _skip_reason(row: Row) -> str | None:
    if "no CUDA" in row.what or "no MPS" in row.what:
        import torch

        if "no CUDA" in row.what and torch.cuda.is_available():
            return "this machine has CUDA"
        mps = getattr(torch.backends, "mps", None)
        if "no MPS" in row.what and mps is not None and mps.is_available():
            return "this machine has MPS"
    return None


ROWS = rows()


def test_the_page_lists_over_a_hundred_bad_inputs_with_distinct_commands():
    assert len(ROWS) >= 110
    assert len({r.command for r in ROWS}) == len(ROWS)
    assert all(r.status in (1, 2, 3, 141) for r in ROWS)


@pytest.mark.parametrize("row", ROWS, ids=[f"{i:03d}" for i in range(len(ROWS))])
def test_bad_input_gives_its_status_and_its_one_line(row, isolated, capfd):
    why = _skip_reason(row)
    if why:
        pytest.skip(why)
    code, err = run_row(row, isolated, capfd)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err, err
    assert code == row.status, (code, err)
    if row.line == "—":
        assert not lines, err
    else:
        assert len(lines) == 1, err
        assert matches(row.line, lines[0]), f"\nexpected: {row.line}\nactual:   {lines[0]}"

"""The house's size rules (ARCHITECTURE.md): no module over 600 lines and no function over 80, so a reader finds one
idea per module and one step per function. Alembic migrations (a schema written out) and the CLI's argparse
``register`` functions (one option per line) are exempt."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "mapfree"
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def _modules(root: Path) -> list[Path]:
    return [p for p in sorted(root.rglob("*.py")) if "migrations" not in p.relative_to(root).parts]


def long_modules(root: Path) -> dict[str, int]:
    """Modules under ``root`` over the line limit, with their line counts."""
    counts = {str(p.relative_to(root)): len(p.read_text().splitlines()) for p in _modules(root)}
    return {name: n for name, n in counts.items() if n > MAX_MODULE_LINES}


def long_functions(root: Path) -> dict[str, int]:
    """Functions under ``root`` over the line limit (``path:line name`` -> lines, decorators left out)."""
    found = {}
    for path in _modules(root):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            if node.name == "register" and path.parent.name == "cli":
                continue
            n = (node.end_lineno or node.lineno) - node.lineno + 1
            if n > MAX_FUNCTION_LINES:
                found[f"{path.relative_to(root)}:{node.lineno} {node.name}"] = n
    return found


def test_no_module_is_longer_than_600_lines():
    assert not (long := long_modules(SRC)), f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_function_is_longer_than_80_lines():
    assert not (long := long_functions(SRC)), f"functions over {MAX_FUNCTION_LINES} lines: {long}"


def test_the_measures_find_long_code_and_honour_the_exemptions(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(85))
    for rel in ("pkg/big.py", "cli/run.py", "cli/serve.py", "db/migrations/versions/0001.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / "pkg/big.py").write_text(
        f"class A:\n    def method(self):\n    {body.replace(chr(10), chr(10) + '    ')}\n"
    )
    (tmp_path / "cli/run.py").write_text(f"def run():\n{body}\n")
    (tmp_path / "cli/serve.py").write_text(f"def register():\n{body}\n" + "\n" * 600)
    (tmp_path / "db/migrations/versions/0001.py").write_text(f"def upgrade():\n{body}\n" + "\n" * 600)
    assert long_functions(tmp_path) == {"pkg/big.py:2 method": 86, "cli/run.py:1 run": 86}
    assert long_modules(tmp_path) == {"cli/serve.py": 686}

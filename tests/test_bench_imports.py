"""The bench scripts' imports, read from their source (nothing imported, nothing run): no circle between the
scripts, and of mapfree only names that exist and are public, outside a short list of private helpers that the
straightforward baseline loops reuse on purpose. ``bench/`` is a folder of scripts, not a package, so the
import contracts of ``lint-imports`` cannot cover it; this test does."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH, SRC = ROOT / "bench", ROOT / "src"

#: Private library helpers the baseline loops use to load the same weight files and keep the same matches as the
#: library does (``module:name``). Anything else private is refused.
PRIVATE_ALLOWED = {
    "mapfree.matching.lightglue:_load_strict",
    "mapfree.matching.lightglue:_remap_glue_keys",
    "mapfree.matching.mast3r:_away_from_border",
}


def _imports(path: Path) -> list[tuple[str, tuple[str, ...]]]:
    """Every import of a file, at any depth (the scripts import lazily): (module, names); names empty for
    ``import module``."""
    out: list[tuple[str, tuple[str, ...]]] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.append((node.module, tuple(a.name for a in node.names)))
        elif isinstance(node, ast.Import):
            out += [(a.name, ()) for a in node.names]
    return out


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` (module -> modules it imports), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                return path[path.index(n) :] + [n]
            if n not in state and (found := visit(n)):
                return found
        path.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def _module_file(module: str) -> Path | None:
    base = SRC.joinpath(*module.split("."))
    return next((p for p in (base.with_suffix(".py"), base / "__init__.py") if p.is_file()), None)


def _defines(path: Path, name: str) -> bool:
    """Whether a module binds ``name`` at its top level (a definition, an assignment or an import) or lists it in
    ``__all__`` (a package that imports it lazily)."""
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if (
            isinstance(node, ast.Assign)
            and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets)
            and isinstance(node.value, (ast.List, ast.Tuple))
            and name in [ast.literal_eval(e) for e in node.value.elts]
        ):
            return True
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name == name:
            return True
        if isinstance(node, (ast.Import, ast.ImportFrom)) and any(
            (a.asname or a.name).split(".")[0] == name for a in node.names
        ):
            return True
        targets = (
            node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        )
        if any(isinstance(t, ast.Name) and t.id == name for t in targets):
            return True
    return False


SCRIPTS = sorted(BENCH.glob("*.py"))


def test_the_cycle_finder_finds_a_circle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_no_bench_script_imports_another_that_imports_it_back():
    local = {p.stem for p in SCRIPTS}
    graph = {p.stem: {m.split(".")[0] for m, _ in _imports(p)} & local - {p.stem} for p in SCRIPTS}
    assert _cycle(graph) is None, f"bench/ import circle: {' -> '.join(_cycle(graph) or [])}"


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_bench_imports_only_public_names_of_mapfree_that_exist(script):
    wrong = []
    for module, names in _imports(script):
        if module.split(".")[0] != "mapfree":
            continue
        path = _module_file(module)
        if path is None:
            wrong.append(f"{module}: no such module")
            continue
        if any(part.startswith("_") for part in module.split(".")):
            wrong.append(f"{module}: a private module")
        for name in names:
            if _module_file(f"{module}.{name}") is not None:
                continue  # a submodule
            if not _defines(path, name):
                wrong.append(f"{module}:{name}: not defined there")
            elif name.startswith("_") and f"{module}:{name}" not in PRIVATE_ALLOWED:
                wrong.append(f"{module}:{name}: private")
    assert not wrong, f"{script.name}: " + "; ".join(wrong)

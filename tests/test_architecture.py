"""House rules over the code itself: layers, import circles and module size read from the source
with `ast` (every import, those inside functions included), and what importing a package pulls in,
checked in a fresh interpreter. The layers are described in `docs/design/extending.md`."""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("strep_core", "strep_bench", "strep_cli", "app")
FORBIDDEN = ("fastapi", "uvicorn", "starlette", "viser", "rerun", "ray")

# Which of the project's packages each package may import (itself included). The command line
# sits above everything; bench and reproduce sit beside the core; the service sits on the core.
ALLOWED: dict[str, frozenset[str]] = {
    "strep_core": frozenset({"strep_core"}),
    "strep_bench": frozenset({"strep_core", "strep_bench"}),
    "app": frozenset({"strep_core", "app"}),
    "strep_cli": frozenset(PACKAGES),
}

MAX_LINES = 500


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _sources() -> dict[str, Path]:
    """Every module of the project's packages: dotted name -> file."""
    return {_module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


MODULES = _sources()


def _type_checking_only(tree: ast.Module) -> set[int]:
    """Line numbers of the imports under ``if TYPE_CHECKING:`` (annotations only, never run)."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            lines |= {
                n.lineno for stmt in node.body for n in ast.walk(stmt) if isinstance(n, ast.Import | ast.ImportFrom)
            }
    return lines


def _imports(name: str, path: Path, *, runtime_only: bool = False) -> Iterator[tuple[str, int]]:
    """(imported module, line) for every import statement of a module, at any depth; with
    ``runtime_only``, not those under ``if TYPE_CHECKING:``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    skip = _type_checking_only(tree) if runtime_only else set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skip:
            continue
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolved against this module's package
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            for alias in node.names:  # ``from pkg import submodule``: the submodule, else pkg itself
                sub = f"{module}.{alias.name}"
                yield (sub if sub in MODULES else module), node.lineno


def _graph() -> dict[str, set[str]]:
    """Module -> the project's modules it imports when it runs (the nearest module for
    ``pkg.mod.name``). Imports for annotations only (``if TYPE_CHECKING:``) make no circle: a
    part handed its owner may name the owner's type. They still count for the layers."""
    graph: dict[str, set[str]] = {name: set() for name in MODULES}
    for name, path in MODULES.items():
        for target, _ in _imports(name, path, runtime_only=True):
            while target and target not in MODULES:
                target = target.rpartition(".")[0]
            if target and target != name:
                graph[name].add(target)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """Strongly connected components of more than one module (Tarjan), iteratively."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[frozenset[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(frozenset(component))
    return found


def test_the_parser_sees_every_package_and_function_level_imports(tmp_path: Path) -> None:
    """The checks below would pass vacuously on an empty graph: prove they see what they check."""
    src = tmp_path / "mod.py"
    src.write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n"
        "    from strep_core import config\n"
        "def f():\n"
        "    import strep_core.geometry\n"
    )
    assert [t for t, _ in _imports("x.mod", src)] == ["typing", "strep_core.config", "strep_core.geometry"]
    assert [t for t, _ in _imports("x.mod", src, runtime_only=True)] == ["typing", "strep_core.geometry"]
    assert {name.split(".")[0] for name in MODULES} == set(PACKAGES)
    graph = _graph()
    # a lazy import inside a function: the CLI's `bench` command imports the benchmark
    assert "strep_bench.bench" in graph["strep_cli.main"]
    # a relative-free ``from package import submodule``
    assert "strep_core.geometry" in graph["strep_core.io.carmen"]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [frozenset("abc")]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_layers_import_only_downwards() -> None:
    """strep_core imports none of the others; strep_bench and app import only strep_core."""
    bad = []
    for name, path in MODULES.items():
        layer = name.split(".")[0]
        for target, line in _imports(name, path):
            top = target.split(".")[0]
            if top in ALLOWED and top not in ALLOWED[layer]:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {target}")
    assert not bad, "imports from a lower layer to a higher one or sideways:\n" + "\n".join(bad)


def test_strep_core_never_imports_web_viewer_or_cluster_code() -> None:
    """Not even lazily, inside a function (rule 1 of the house; the fresh-interpreter test
    below sees only what importing pulls in)."""
    bad = [
        f"{path.relative_to(ROOT)}:{line} imports {target}"
        for name, path in MODULES.items()
        if name.split(".")[0] in ("strep_core", "strep_bench")
        for target, line in _imports(name, path)
        if target.split(".")[0] in FORBIDDEN and not (name == "strep_bench.ray_runner" and target == "ray")
    ]
    assert not bad, "\n".join(bad)


def test_no_import_circles() -> None:
    cycles = _cycles(_graph())
    assert not cycles, f"import circles: {[sorted(c) for c in cycles]}"


def test_no_module_over_500_lines() -> None:
    sizes = {name: len(path.read_text().splitlines()) for name, path in MODULES.items()}
    over = {name: n for name, n in sizes.items() if n > MAX_LINES}
    assert not over, f"modules over {MAX_LINES} lines: {over}; split them along their seams"


def _fresh(code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


@pytest.mark.parametrize("package", ["strep_core", "strep_bench"])
def test_core_and_bench_import_no_web_viewer_or_cluster_code(package: str) -> None:
    """Every module of the package imported in a fresh interpreter, and the method table filled."""
    modules = sorted(name for name in MODULES if name.split(".")[0] == package)
    code = (
        "import importlib, sys\n"
        f"for name in {modules!r}:\n"
        "    importlib.import_module(name)\n"
        "from strep_core.methods import available\n"
        "available()\n"
        f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {FORBIDDEN!r})\n"
        "print(','.join(bad))\n"
    )
    out = _fresh(code)
    assert out == "", f"{package} pulled in: {out}"


def test_importing_the_package_and_the_command_line_is_light() -> None:
    """`import strep_core` and the CLI must not drag in Open3D or torch (``strep --help`` starts fast)."""
    out = _fresh("import sys, strep_core, strep_cli; print(sorted({'open3d', 'torch'} & set(sys.modules)))")
    assert out == "[]"

"""The package's shape, read from the source with `ast`: no import circle, no import from a lower
layer into a higher one (the layers of docs/architecture.md), and no function longer than 80
lines outside numba/CUDA kernels."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import latentz

ROOT = Path(latentz.__file__).parent

#: Layers, bottom up; a module may import only from its own layer or below.
LAYERS = (
    ("_version", "_shared"),
    ("camera", "io", "detect"),
    ("fit", "simulate"),
    ("calibration",),
    ("localization", "motion", "analysis"),
    ("validation", "report"),
    ("cli", "viewer"),
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(tree: ast.AST, package: str) -> list[str]:
    """Every module imported anywhere in ``tree`` (function bodies and ``if TYPE_CHECKING:``
    included: a type hint's import is an arrow too); ``from a import b`` counts as ``a.b``
    where ``b`` is a module."""
    found: list[str] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(
                    package.split(".")[: len(package.split(".")) - node.level + 1]
                    + ([base] if base else [])
                )
            found.extend(f"{base}.{alias.name}" for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


@functools.cache
def import_graph() -> dict[str, set[str]]:
    """``{module: {latentz modules it imports}}`` over every file of ``src/latentz``."""
    files = {_module_name(p): p for p in ROOT.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for imported in _imports(ast.parse(path.read_text()), package):
            # `from a import b`: the module a.b if it exists, else a itself
            if imported in files:
                targets.add(imported)
            elif imported.rpartition(".")[0] in files and imported.startswith("latentz"):
                targets.add(imported.rpartition(".")[0])
        graph[name] = targets - {name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return found


def _layer(module: str) -> int | None:
    top = module.split(".")[1] if module.count(".") else ""
    for level, names in enumerate(LAYERS):
        if top in names:
            return level
    return None


def test_the_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_graph_sees_function_level_and_type_hint_imports():
    tree = ast.parse("def f():\n    from latentz.io import tables\n")
    assert "latentz.io.tables" in _imports(tree, "latentz.x")
    guarded = ast.parse(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import latentz.cli\n"
    )
    assert "latentz.cli" in _imports(guarded, "latentz.x")


def test_no_import_circle():
    assert cycles(import_graph()) == []


def test_every_top_level_folder_has_a_layer():
    tops = {p.name for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    tops |= {p.stem for p in ROOT.glob("*.py") if p.stem != "__init__"}
    assert {t for t in tops if _layer(f"latentz.{t}") is None} == set()


def test_no_import_runs_up_a_layer():
    graph = import_graph()
    upward = {
        module: sorted(t for t in targets if (_layer(t) or 0) > _layer(module))
        for module, targets in graph.items()
        if _layer(module) is not None  # the package's own __init__ (the public API) is above all
    }
    assert {m: u for m, u in upward.items() if u} == {}


#: The longest function body (lines, docstring excluded) outside numba/CUDA kernels.
MAX_FUNCTION_LINES = 80


#: Decorators of numba/CUDA kernels, which may be long (a kernel cannot call Python steps).
KERNEL_DECORATORS = ("numba.njit", "numba.jit", "njit", "cuda.jit", "numba.cuda.jit")


def _is_kernel(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """Decorated with numba's ``njit``/``jit`` or ``cuda.jit``, called or not."""
    return any(
        ast.unparse(d.func if isinstance(d, ast.Call) else d) in KERNEL_DECORATORS
        for d in node.decorator_list
    )


def _body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from the first statement after the docstring to the end of the function."""
    body = node.body
    if (
        body
        and isinstance(body[0], ast.Expr)
        and isinstance(body[0].value, ast.Constant)
        and isinstance(body[0].value.value, str)
    ):
        body = body[1:]
    return body[-1].end_lineno - body[0].lineno + 1 if body else 0


def long_functions(tree: ast.AST) -> list[tuple[str, int, int]]:
    """``(name, line, body lines)`` of every function in ``tree`` longer than the limit."""
    return [
        (node.name, node.lineno, _body_lines(node))
        for node in ast.walk(tree)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        and not _is_kernel(node)
        and _body_lines(node) > MAX_FUNCTION_LINES
    ]


def test_the_length_check_finds_a_planted_long_function():
    statements = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES + 1))
    script = f'def script():\n    """Doc."""\n{statements}\n'
    assert [(name, n) for name, _, n in long_functions(ast.parse(script))] == [
        ("script", MAX_FUNCTION_LINES + 1)
    ]
    short = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    assert long_functions(ast.parse(f'def steps():\n    """Doc."""\n{short}\n')) == []
    kernel = f"import numba\n@numba.njit(cache=True)\ndef kernel():\n{statements}\n"
    assert long_functions(ast.parse(kernel)) == []
    assert long_functions(ast.parse(f"@cuda.jit\ndef k():\n{statements}\n")) == []


def test_no_function_is_a_script():
    offenders = [
        f"{path.relative_to(ROOT.parent)}:{line} {name} ({n} lines)"
        for path in sorted(ROOT.rglob("*.py"))
        for name, line, n in long_functions(ast.parse(path.read_text()))
    ]
    assert not offenders, (
        f"{len(offenders)} function(s) over {MAX_FUNCTION_LINES} lines; split each into named "
        "steps:\n" + "\n".join(offenders)
    )

"""The package's layers: kernels < core < io < studies < commands, imports only downward, no cycles.

Every import statement counts, also one inside a function (a function-level import that dodges a
cycle at load time is still a cycle in the design), and so does ``importlib.import_module`` of a
package module. The repository's source tree is read, not the installed package, so the test sees
the files a change touches.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
LAYERS = {"kernels": 0, "core": 1, "io": 2, "studies": 3, "commands": 4}


def _modules() -> dict[str, pathlib.Path]:
    """Dotted name -> file for every module of softsim_warp (kernels/ is installed as softsim_warp.kernels)."""
    out = {}
    for base, prefix in ((ROOT / "softsim_warp", "softsim_warp"), (ROOT / "kernels", "softsim_warp.kernels")):
        for path in sorted(base.rglob("*.py")):
            parts = list(path.relative_to(base).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([prefix, *parts])] = path
    return out


MODULES = _modules()


def _resolve(name: str) -> str | None:
    """The package module that ``import name`` loads last (the deepest existing prefix)."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in MODULES:
            return candidate
        parts.pop()
    return None


def _imports(module: str) -> set[str]:
    path = MODULES[module]
    is_package = path.name == "__init__.py"
    package = module if is_package else module.rpartition(".")[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            # "from pkg import sub" imports the submodule pkg.sub when there is one.
            names = [f"{stem}.{a.name}" if f"{stem}.{a.name}" in MODULES else stem for a in node.names]
        elif (
            isinstance(node, ast.Call)
            and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            names = [node.args[0].value]
        else:
            continue
        for name in names:
            target = _resolve(name) if name.startswith("softsim_warp") else None
            if target is not None and target != module:
                targets.add(target)
    return targets


GRAPH = {m: _imports(m) for m in MODULES}


def _layer(module: str) -> int | None:
    parts = module.split(".")
    return LAYERS.get(parts[1]) if len(parts) > 1 else None


def _cycles() -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in GRAPH:
        if v not in index:
            visit(v)
    return out


def test_every_module_is_in_a_layer():
    """Apart from the package's front door (softsim_warp, its __main__), each module sits in a layer."""
    outside = [m for m in MODULES if _layer(m) is None and m not in ("softsim_warp", "softsim_warp.__main__")]
    assert outside == []


def test_no_import_cycles():
    assert _cycles() == []


def test_imports_only_go_down():
    upward = [
        f"{m} -> {t}"
        for m, targets in GRAPH.items()
        for t in targets
        if _layer(m) is not None and (_layer(t) is None or _layer(t) > _layer(m))
    ]
    assert upward == []


def test_the_checker_sees_function_level_and_dynamic_imports(tmp_path):
    """The parser catches function-level and dynamic imports, the shapes a hidden cycle takes (guards
    the test itself)."""
    src = "def f():\n    from ..io import scene\n    importlib.import_module('softsim_warp.commands.cli')\n"
    MODULES["softsim_warp.core._probe"] = tmp_path / "_probe.py"
    try:
        (tmp_path / "_probe.py").write_text(src)
        assert _imports("softsim_warp.core._probe") == {"softsim_warp.io.scene", "softsim_warp.commands.cli"}
    finally:
        del MODULES["softsim_warp.core._probe"]


@pytest.mark.parametrize("module", ["softsim_warp.core", "softsim_warp.io", "softsim_warp.studies", "softsim_warp.commands"])
def test_layer_packages_exist(module):
    assert module in MODULES


def test_benchmarks_and_docs_scripts_use_the_library_not_the_commands():
    """benchmarks/, docs/ and examples/ scripts measure through library code (softsim_warp.studies and
    below), not through the command modules, which only parse, call and print."""
    scripts = [*sorted((ROOT / "benchmarks").glob("*.py")), *sorted((ROOT / "docs").glob("*.py")),
               *sorted((ROOT / "examples").glob("*.py"))]
    assert scripts
    found = []
    for path in scripts:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            found += [f"{path.name}: {n}" for n in names if n == "softsim_warp.commands" or n.startswith("softsim_warp.commands.")]
    assert found == []


def test_every_package_is_installed():
    """pyproject.toml lists every package of softsim_warp/ (one missing there is left out of an install)."""
    import tomllib  # noqa: PLC0415

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    base = ROOT / "softsim_warp"
    found = {".".join(["softsim_warp", *init.parent.relative_to(base).parts]) for init in base.rglob("__init__.py")}
    assert found - listed == set()


def test_star_import_and_all():
    """``from softsim_warp import *`` binds exactly ``__all__``, and every name in it is public API."""
    import softsim_warp

    namespace = {}
    exec("from softsim_warp import *", namespace)
    namespace.pop("__builtins__")
    assert sorted(namespace) == sorted(softsim_warp.__all__)
    assert len(set(softsim_warp.__all__)) == len(softsim_warp.__all__)
    for name in softsim_warp.__all__:
        assert getattr(softsim_warp, name).__doc__ or name == "INTEGRATORS", name

"""No test seam in the package: no hook a test fills, no pause or marker a test asks for, and no
environment variable that only tests set. Tests reach the phases they need from outside
(``tests/hooks/sitecustomize.py`` in their subprocesses, monkeypatching, explicit arguments such as
a Stepper's ``on_warm_up``). The repository's source tree is read, as tests/test_layering.py does."""

from __future__ import annotations

import ast
import pathlib
import re

from tests.subprocess_hooks import VARIABLES

ROOT = pathlib.Path(__file__).resolve().parents[1]
SOURCES = sorted([*(ROOT / "softsim_warp").rglob("*.py"), *(ROOT / "kernels").rglob("*.py")])

# Seams that would tie the package to its tests: a pause at named phases, a global of the running
# command's signals, a list of warm-up hooks the command line fills, a sweep task's marks.
SEAM_NAMES = ("pause_for_test", "TEST_PAUSES", "_test_pauses", "ACTIVE_SIGNALS", "WARM_UP_HOOKS", "_test_hooks",
              "softsim-test:")


def _environment_reads(tree: ast.AST) -> set[str]:
    """Names of the environment variables a module reads: ``os.environ.get("X")``, ``os.environ["X"]``,
    ``os.getenv("X")``, ``"X" in os.environ`` (``environ`` and ``getenv`` however imported)."""

    def is_environ(node):
        return (isinstance(node, ast.Attribute) and node.attr == "environ") or (
            isinstance(node, ast.Name) and node.id == "environ")

    names = set()
    for node in ast.walk(tree):
        key = None
        if isinstance(node, ast.Call) and node.args:
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            from_environ = isinstance(f, ast.Attribute) and is_environ(f.value)
            if (from_environ and name in ("get", "pop", "setdefault")) or name == "getenv":
                key = node.args[0]
        elif isinstance(node, ast.Subscript) and is_environ(node.value):
            key = node.slice
        elif isinstance(node, ast.Compare) and any(is_environ(c) for c in node.comparators):
            key = node.left
        if isinstance(key, ast.Constant) and isinstance(key.value, str):
            names.add(key.value)
    return names


def test_the_scan_sees_the_package():
    assert len(SOURCES) > 50
    reads = set()
    for path in SOURCES:
        reads |= _environment_reads(ast.parse(path.read_text(), str(path)))
    assert "WARP_CACHE_PATH" in reads  # the scan finds the variables the package does read
    sample = 'import os\nos.environ.get("A")\nos.environ["B"]\nos.getenv("C")\n"D" in os.environ\n'
    assert _environment_reads(ast.parse(sample)) == {"A", "B", "C", "D"}


def test_no_test_seam_in_the_package():
    found = []
    for path in SOURCES:
        text = path.read_text()
        rel = path.relative_to(ROOT)
        for name in SEAM_NAMES:
            for m in re.finditer(re.escape(name), text):
                found.append(f"{rel}:{text.count(chr(10), 0, m.start()) + 1}: {name}")
        # Any variable named for tests, whether read or only mentioned (a variable read through a
        # helper the scan does not recognise would still be named somewhere).
        for m in re.finditer(r"\b[A-Z][A-Z0-9_]*TEST[A-Z0-9_]*\b", text):
            found.append(f"{rel}:{text.count(chr(10), 0, m.start()) + 1}: {m.group(0)}")
        for name in _environment_reads(ast.parse(text, str(path))):
            if name in VARIABLES or "TEST" in name:
                found.append(f"{rel}: reads the environment variable {name}, which only tests set")
    assert found == [], "test seams in the package:\n" + "\n".join(found)

"""The integrator registry (core/methods.py): the one place a method is declared, and its tableaux.

Pure Python: no kernel runs here. tests/test_integrators.py measures every registered explicit
method's order through the real integrator.
"""

from __future__ import annotations

import ast
import math
import pathlib
from fractions import Fraction

import numpy as np
import pytest

from softsim_warp.core import methods
from softsim_warp.core.methods import EXPLICIT_NAMES, MAX_STAGES, METHODS, NAMES, method

ROOT = pathlib.Path(__file__).resolve().parents[1]
REGISTRY = ROOT / "softsim_warp" / "core" / "methods.py"


def _docstring_nodes(tree) -> set[int]:
    """ids of the string constants that are docstrings (module, class, function)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                out.add(id(first.value))
    return out


def name_literals(path: pathlib.Path, names, root=ROOT) -> list[str]:
    """``file:line: 'name'`` for every string literal in ``path`` that is a method name, docstrings
    aside (they describe; code that picks a method must go through the registry)."""
    tree = ast.parse(path.read_text(), str(path))
    docstrings = _docstring_nodes(tree)
    return sorted(
        f"{path.relative_to(root)}:{node.lineno}: {node.value!r}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names
        and id(node) not in docstrings
    )


def test_method_names_are_written_only_in_the_registry():
    # Adding or renaming an integrator touches core/methods.py alone: the scene schema, CLI choices,
    # stability analysis, plots, resources and sweeps read names from it. Docstrings may name
    # methods; code may not (not even an f-string part equal to a name, which ast sees as a constant).
    found = []
    for base in (ROOT / "softsim_warp", ROOT / "kernels"):
        for path in sorted(base.rglob("*.py")):
            if path != REGISTRY:
                found += name_literals(path, set(NAMES))
    assert found == []


def test_the_name_scan_sees_literals_and_skips_docstrings(tmp_path):
    # Guards the test above: it must flag a table keyed by names and a comparison, not a docstring.
    src = tmp_path / "sample.py"
    src.write_text('"""Uses ``rk4``."""\n'
                   'def f(m):\n    """rk4"""\n    return m == "rk4"\n'
                   'COLORS = {"euler": 1}\n')
    hits = name_literals(src, {"rk4", "euler"}, root=tmp_path)
    assert hits == ["sample.py:4: 'rk4'", "sample.py:5: 'euler'"]


def test_names_are_unique_and_the_accessors_agree():
    assert len(set(NAMES)) == len(NAMES) == len(METHODS)
    assert EXPLICIT_NAMES == tuple(m.name for m in METHODS if m.explicit)
    assert set(methods.COLORS) == set(NAMES)
    assert len(set(methods.COLORS.values())) == len(NAMES)  # each method its own colour
    assert len({m.label for m in METHODS}) == len(NAMES)
    for m in METHODS:
        assert method(m.name) is m
    assert methods.DEFAULT in METHODS and methods.REFERENCE in METHODS
    # The reference of accuracy runs is the most accurate explicit method.
    assert methods.REFERENCE.order == max(m.order for m in METHODS if m.explicit)


def test_unknown_name_is_one_line_listing_the_allowed_ones():
    with pytest.raises(ValueError) as info:
        method("rk5")
    message = str(info.value)
    assert "\n" not in message and "'rk5'" in message
    assert message.endswith(", ".join(NAMES))
    with pytest.raises(ValueError):
        method(None)


def test_methods_are_frozen():
    with pytest.raises(AttributeError):
        methods.RK4.order = 5


@pytest.mark.parametrize("m", [m for m in METHODS if m.explicit], ids=lambda m: m.name)
def test_explicit_tableau_is_consistent(m):
    assert len(m.c) == len(m.b) == m.stages <= MAX_STAGES
    assert all(isinstance(x, Fraction) for x in m.c + m.b)
    assert m.c[0] == 0  # the first stage is evaluated at y_n
    assert sum(m.b) == 1  # consistency: the method is at least first order
    assert m.contact_beta in (0.0, 1.0)


def _tableau_step(m, z_h, y):
    """One step of ``m``'s tableau on y' = lam y, with z_h = h lam (the stage rule of the stage kernel)."""
    c, b = m.tableau
    k_prev, out = 0.0, y
    for c_s, b_s in zip(c, b):
        k = z_h * (y + c_s * k_prev)  # h k_s
        out = out + b_s * k
        k_prev = k
    return out


def _observed_order(m, error_at) -> float:
    """log2 of the error ratio of steps h and h/2, fitted over three halvings."""
    errors = [error_at(0.1 / 2**i) for i in range(4)]
    return float(np.polyfit(np.log2([0.1 / 2**i for i in range(4)]), np.log2(errors), 1)[0])


@pytest.mark.parametrize("m", [m for m in METHODS if m.explicit and not m.partitioned], ids=lambda m: m.name)
def test_tableau_order_on_a_linear_ode(m):
    # y' = -y, y(0) = 1 on [0, 1]: the global error of an order-p method falls as h^p (exact: e^-1).
    def error_at(h):
        y = 1.0
        for _ in range(round(1.0 / h)):
            y = _tableau_step(m, -h, y)
        return abs(y - math.exp(-1.0))

    assert _observed_order(m, error_at) == pytest.approx(m.order, abs=0.1)


@pytest.mark.parametrize("m", [m for m in METHODS if m.partitioned], ids=lambda m: m.name)
def test_partitioned_order_on_an_oscillator(m):
    # A partitioned method has no tableau of its own (a placeholder): its rule, v first and x with the
    # new v, is measured on x'' = -x, x(0) = 1, v(0) = 0 on [0, 1] (exact: cos 1).
    def error_at(h):
        x, v = 1.0, 0.0
        for _ in range(round(1.0 / h)):
            v = v - h * x
            x = x + h * v
        return abs(x - math.cos(1.0))

    assert _observed_order(m, error_at) == pytest.approx(m.order, abs=0.1)
    assert m.tableau == ((0.0,), (1.0,))


@pytest.mark.parametrize("m", [m for m in METHODS if m.explicit and not m.partitioned], ids=lambda m: m.name)
def test_stability_polynomial_is_the_tableau_on_y_lam_y(m):
    # R(z) from the exact fractions equals one step of the float tableau on y' = lam y, and for these
    # methods (stages = order <= 4) the Taylor series of e^z up to z^order.
    coeffs = m.stability_polynomial
    assert coeffs == tuple(1.0 / math.factorial(k) for k in range(m.order + 1))
    z = np.array([-0.3 + 0.2j, -1.7 + 1.1j, 0.5j, -2.5])
    np.testing.assert_allclose(np.polynomial.polynomial.polyval(z, coeffs), _tableau_step(m, z, 1.0), rtol=1e-14)


def test_stability_analysis_reads_the_registry():
    from softsim_warp.core import stability_analysis as sa  # noqa: PLC0415

    for m in METHODS:
        if m.partitioned:
            with pytest.raises(ValueError, match="partitioned"):
                sa.stability_function(m.name)
        elif m.explicit:
            np.testing.assert_allclose(sa.stability_function(m.name)(-1.0), math.fsum(
                (-1.0) ** k / math.factorial(k) for k in range(m.order + 1)), rtol=1e-15)
        else:  # backward Euler: 1 / (1 - z)
            assert sa.stability_function(m.name)(-1.0) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="unknown integrator"):
        sa.stability_function("rk5")


def test_scene_schema_and_cli_read_the_registry():
    from softsim_warp.commands.common import parse_methods  # noqa: PLC0415
    from softsim_warp.core.errors import CommandLineError, SceneError  # noqa: PLC0415
    from softsim_warp.io import scene  # noqa: PLC0415

    assert scene.INTEGRATORS == NAMES
    assert parse_methods(",".join(NAMES)) == list(NAMES)
    with pytest.raises(CommandLineError, match=", ".join(NAMES)):
        parse_methods("rk5")
    for n in NAMES:
        assert scene.load_scene("jelly_drop", [f"simulation.integrator={n}"]).sim["integrator"] == n
    with pytest.raises(SceneError, match="simulation.integrator: must be one of"):
        scene.load_scene("jelly_drop", ["simulation.integrator=rk5"])
    assert scene.load_scene("jelly_drop").data["simulation"]["integrator"] in NAMES


def test_resources_read_stages_from_the_registry():
    from softsim_warp.io import resources  # noqa: PLC0415

    # The size checks assume the method with the largest buffers: the implicit one, else the most stages.
    assert resources.heaviest(NAMES) == methods.IMPLICIT.name
    most = max((m for m in METHODS if m.explicit), key=lambda m: m.stages)
    assert resources.heaviest(EXPLICIT_NAMES) == most.name
    # One-stage methods keep no stage state; more stages add the stage state and the RK accumulators.
    one = [m.name for m in METHODS if m.stages == 1]
    more = [m.name for m in METHODS if m.stages is not None and m.stages > 1]
    assert one and more
    for a in one:
        for b in more:
            assert resources._device_per_particle(8, a) < resources._device_per_particle(8, b)
    with pytest.raises(ValueError, match="unknown integrator"):
        resources.heaviest(["rk5"])

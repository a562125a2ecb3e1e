"""The integrator registry: every time-stepping method, declared once.

Each :class:`Method` says what the rest of the package needs to know about one integrator: its
name (as written in scene files and on the command line), a label for tables, its order, its force
evaluations per step, whether it is explicit, its Butcher tableau, its contact gain, its colour in
plots and how to make it. The scene schema, the CLI's choices, the stability analysis, the plots,
the resource estimate and the sweeps read these; nothing else lists method names (a test greps the
package for name literals outside this file).

Adding an integrator: write its step (an explicit method with a lower-triangular tableau whose only
nonzero a_{s,j} is the subdiagonal a_{s,s-1} = c_s needs no new kernel: the stage kernel runs any
such tableau of up to :data:`MAX_STAGES` stages), add a :class:`Method` below and put it in
:data:`METHODS`. See docs/ARCHITECTURE.md, "Adding an integrator".

How a method is made follows from ``explicit``: ``make_integrator`` (core/stepper.py) gives an explicit
method to :class:`~softsim_warp.core.integrators.ExplicitIntegrator`, which runs it from its tableau
alone, and the implicit one to :class:`~softsim_warp.core.implicit.ImplicitIntegrator`. The
integrator modules import this one, so it imports none of them (and nothing from io or commands).
"""

from __future__ import annotations

import types
from dataclasses import dataclass
from fractions import Fraction

# Stages an explicit tableau may have: the size of the per-world tableau arrays the stage kernel reads.
MAX_STAGES = 4


@dataclass(frozen=True)
class Method:
    """One integrator.

    Attributes:
        name: the name in scene files (``simulation.integrator``), on the command line and in outputs.
        label: a short human name for tables and legends.
        order: its order of accuracy (global error ~ dt^order on smooth problems).
        stages: force evaluations per step; None where it is not fixed (the implicit method's
            Newton iterations and CG solves vary with the options).
        explicit: True for an explicit method; False for the implicit one (backward Euler:
            stability function ``1/(1 - z)``, A-stable, solved by Newton and CG).
        c, b: the Butcher tableau of an explicit method, exact: stage s is evaluated at
            ``y_n + h c_s k_{s-1}`` and ``y_{n+1} = y_n + h sum_s b_s k_s`` (every a_{s,j} is 0 but
            the subdiagonal a_{s,s-1} = c_s). Empty for the implicit method.
        partitioned: True for symplectic Euler, which updates v first and x with the new v; its
            tableau is then a placeholder (one stage, b = 1) and it has no stability function R(z).
        contact_beta: position gain of a constant acceleration a over one step,
            ``x_{n+1} = ... + beta h^2 a``, that the post-step contact response adds for the
            contact force it applies: 1 when x is updated with v_{n+1}, 0 for explicit Euler
            (x_{n+1} = x_n + h v_n). Midpoint and RK4 would need sum_s b_s c_s = 1/2, but their stage
            states already hold the contact force of particles resting on terrain
            (``contact.filter_stage_contacts``), so their positions carry it and the response adds nothing.
        color: its matplotlib colour in every plot.
    """

    name: str
    label: str
    order: int
    stages: int | None
    explicit: bool
    contact_beta: float
    color: str
    c: tuple[Fraction, ...] = ()
    b: tuple[Fraction, ...] = ()
    partitioned: bool = False

    @property
    def tableau(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """``(c, b)`` as floats (each the correctly rounded value of the exact fraction)."""
        return tuple(float(x) for x in self.c), tuple(float(x) for x in self.b)

    @property
    def stability_polynomial(self) -> tuple[float, ...] | None:
        """Coefficients (ascending powers of z) of the stability function ``R(z)`` of an explicit,
        unpartitioned method: one step on ``y' = lambda y`` gives ``y_{n+1} = R(h lambda) y_n``.
        Computed exactly from the tableau, then rounded. None for the partitioned and implicit methods.
        """
        if not self.explicit or self.partitioned:
            return None
        # With K_s = k_s / (lambda y_n): K_s = 1 + z c_s K_{s-1} (stage s is evaluated at
        # y_n + h c_s k_{s-1}) and R = 1 + z sum_s b_s K_s. Polynomials in z as lists of Fractions.
        poly = [Fraction(1)]
        k_prev: list[Fraction] = []
        for c_s, b_s in zip(self.c, self.b):
            k = [Fraction(1)] + [c_s * a for a in k_prev]  # k_s / (lambda y_n) = 1 + z c_s k_{s-1}
            for i, a in enumerate(k):
                term = b_s * a  # z * b_s * k_s: shifted one power up
                if i + 1 < len(poly):
                    poly[i + 1] += term
                else:
                    poly.append(term)
            k_prev = k
        while len(poly) > 1 and poly[-1] == 0:
            poly.pop()
        return tuple(float(a) for a in poly)


F = Fraction

EULER = Method(
    name="euler", label="explicit Euler", order=1, stages=1, explicit=True, contact_beta=0.0,
    color="tab:red", c=(F(0),), b=(F(1),),
)
SYMPLECTIC = Method(
    name="symplectic", label="symplectic Euler", order=1, stages=1, explicit=True, contact_beta=1.0,
    color="tab:orange", c=(F(0),), b=(F(1),), partitioned=True,
)
MIDPOINT = Method(
    name="midpoint", label="midpoint", order=2, stages=2, explicit=True, contact_beta=0.0,
    color="tab:green", c=(F(0), F(1, 2)), b=(F(0), F(1)),
)
RK4 = Method(
    name="rk4", label="RK4", order=4, stages=4, explicit=True, contact_beta=0.0,
    color="tab:blue", c=(F(0), F(1, 2), F(1, 2), F(1)), b=(F(1, 6), F(1, 3), F(1, 3), F(1, 6)),
)
IMPLICIT = Method(
    name="implicit", label="implicit Euler", order=1, stages=None, explicit=False, contact_beta=1.0,
    color="tab:purple",
)

# Every method, in the order of tables, plots and CLI help.
METHODS: tuple[Method, ...] = (EULER, SYMPLECTIC, MIDPOINT, RK4, IMPLICIT)
NAMES: tuple[str, ...] = tuple(m.name for m in METHODS)
EXPLICIT_NAMES: tuple[str, ...] = tuple(m.name for m in METHODS if m.explicit)
COLORS = types.MappingProxyType({m.name: m.color for m in METHODS})

# The scene's integrator when it names none.
DEFAULT = SYMPLECTIC
# The reference of accuracy measurements and sweeps (run in float64 at a small step): the highest order.
REFERENCE = RK4

_BY_NAME = {m.name: m for m in METHODS}


def method(name: str) -> Method:
    """The method called ``name``; a ValueError of one line listing the names otherwise."""
    try:
        return _BY_NAME[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown integrator {name!r}; choose from {', '.join(NAMES)}") from None


"""Largest stable step of a whole model, matrix-free in NumPy (Lanczos).

:mod:`.stability_analysis` linearises a jelly at rest, ``M dx'' = K dx + C dv``, and finds each
integrator's largest stable step from the dense eigenproblem. That costs ``(6N)^3`` and is limited
to a few hundred particles, yet the limit depends on the jelly's size: the stiffest modes of a
10x10x10 lattice are 18 % stiffer than those of a 4x4x4 one, because a small lattice is mostly
boundary. This module predicts the limit of the model itself, at any size:

1. The spring Jacobians at the start positions, ``S = -dK`` and ``D = -C``, are those of the
   implicit integrator's per-spring blocks (kernels/springs.py ``spring_jacobian``), applied to a
   vector straight from the spring list in NumPy (:class:`SpringOperator`, one pass over the
   springs for both); nothing is assembled and no Warp kernel runs, so a scene's dt can be checked
   before anything compiles (``io/stable_step.py``).
2. Lanczos with full reorthogonalisation on the mass-weighted ``St = M^-1/2 S M^-1/2`` (fixed
   particles, inverse mass 0, removed) builds an orthonormal Krylov basis ``V`` (when the springs'
   ``kd / ks`` differ, every other expansion uses ``Dt`` instead, so that the basis also holds the
   directions the dampers couple). Its extreme Ritz values converge first, at both ends of the
   spectrum, which is where the limiting modes are: the stiffest modes limit every explicit method,
   and for explicit Euler the softest underdamped ones can too. Every ``check_every`` iterations
   the projected system is analysed (:func:`_estimates`); iteration stops when the largest Ritz
   value has moved by less than ``tol`` and each requested method's step by less than ``dt_tol``
   (relative) since the last check.
3. The damped system projected on ``V``, ``a'' = -V^T St V a - V^T Dt V a'``, is small (``k x k``,
   ``k`` the number of iterations) and goes through the dense analysis of
   :mod:`.stability_analysis` (deflation of free modes, per-eigenvalue limits, the symplectic step
   map). When every spring has the same ``kd / ks``, ``Dt = (kd/ks) St`` and the projection is exact
   in the Krylov space; otherwise ``V^T Dt V`` is the Rayleigh-Ritz approximation of the damping.

The projections are filled a column per iteration (the first Gram-Schmidt pass gives it), so an
iteration costs one pass over the springs and a few products with the basis so far. The basis costs
``k`` vectors of ``3N`` float64 on the host; :data:`MEMORY_BUDGET` caps ``k``, which limits the
accuracy only for jellies of millions of particles (the report says how many iterations ran and
whether they converged).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import stability_analysis as sa
from .methods import NAMES, method
from .model import Model, ModelBuilder

MAX_ITERATIONS = 300
MIN_ITERATIONS = 30
CHECK_EVERY = 10
DEFAULT_TOL = 1.0e-4
DEFAULT_DT_TOL = 1.0e-3
MEMORY_BUDGET = 2 << 30  # bytes of Lanczos basis on the host
SEED = 0


@dataclass
class Prediction:
    """Largest stable dt per method, and how the Lanczos iteration went."""

    dt: dict
    iterations: int
    converged: bool
    proportional_damping: bool
    max_frequency: float  # sqrt of the largest eigenvalue of M^-1 S [rad/s]


class SpringOperator:
    """Products with the mass-weighted stiffness and damping Jacobians of a spring list, in NumPy.

    The blocks are those of the implicit integrator (kernels/springs.py ``spring_jacobian``):
    ``S = ks [d^d^T + max(0, 1 - r/|d|)(I - d^d^T)]`` and ``D = kd d^d^T`` per spring, entering at
    ``(a, a)``, ``(b, b)`` with ``+`` and at ``(a, b)``, ``(b, a)`` with ``-``. Nothing is assembled
    and no Warp kernel runs: a scene's dt is checked before any kernel compiles. Vectors are flat
    ``(3N,)`` float64, component-major; fixed particles (inverse mass 0) get zero rows and columns.
    """

    def __init__(self, points, pairs, rest, ks, kd, inv_mass):
        points = np.asarray(points, dtype=np.float64)
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        self.n = points.shape[0]
        self.a, self.b = pairs[:, 0], pairs[:, 1]
        d = points[self.a] - points[self.b]
        length = np.linalg.norm(d, axis=1)
        live = length > 0.0  # coincident particles: no direction, zero blocks (as spring_jacobian)
        safe = np.where(live, length, 1.0)
        self.u = np.ascontiguousarray(np.where(live[:, None], d / safe[:, None], 0.0).T)  # (3, S)
        ks = np.broadcast_to(np.asarray(ks, dtype=np.float64), self.a.shape)
        kd = np.broadcast_to(np.asarray(kd, dtype=np.float64), self.a.shape)
        transverse = np.where(live, np.maximum(1.0 - np.broadcast_to(rest, self.a.shape) / safe, 0.0), 0.0)
        self.s_along = np.where(live, ks * (1.0 - transverse), 0.0)
        self.s_across = np.where(live, ks * transverse, 0.0)
        self.d_along = np.where(live, kd, 0.0)
        inv_mass = np.broadcast_to(np.asarray(inv_mass, dtype=np.float64), (self.n,))
        self.free = inv_mass > 0.0
        self.w = np.sqrt(np.where(self.free, inv_mass, 0.0))
        self.ks, self.kd = ks, kd
        self.has_across = bool(np.any(self.s_across))
        self.products = 0  # spring-list passes, the work bound the tests check

    def spring_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """Each spring's ``(S, D)`` as ``(springs, 3, 3)`` arrays, from the factors :meth:`apply` uses
        (``S = s_along d^d^T + s_across I``, ``D = kd d^d^T``): the blocks that
        tests/test_kernels_implicit.py compares with ``spring_jacobian``."""
        along = np.einsum("is,js->sij", self.u, self.u)
        identity = np.eye(3)[None]
        stiffness = self.s_along[:, None, None] * along + self.s_across[:, None, None] * identity
        return stiffness, self.d_along[:, None, None] * along

    def _scatter(self, f):
        """``y_a += f``, ``y_b -= f`` per spring, mass-weighted: ``f`` and the result component-major."""
        return np.concatenate([self.w * (np.bincount(self.a, fc, self.n) - np.bincount(self.b, fc, self.n)) for fc in f])

    def apply(self, v: np.ndarray, damping=True):
        """``(M^-1/2 S M^-1/2 v, M^-1/2 D M^-1/2 v)`` in one pass over the springs (the second None
        without ``damping``). Vectors are component-major: all x, then all y, then all z."""
        self.products += 1
        p = self.w * v.reshape(3, self.n)
        delta = [pc[self.a] - pc[self.b] for pc in p]
        along = delta[0] * self.u[0] + delta[1] * self.u[1] + delta[2] * self.u[2]
        stretch = self.s_along * along
        f = [stretch * uc for uc in self.u]
        if self.has_across:
            f = [fc + self.s_across * dc for fc, dc in zip(f, delta)]
        sv = self._scatter(f)
        if not damping:
            return sv, None
        rate = self.d_along * along
        return sv, self._scatter([rate * uc for uc in self.u])

    @classmethod
    def of_model(cls, model: Model) -> "SpringOperator":
        """The operator of a model's springs at its start positions (host copies; no kernel runs)."""
        return cls(model.particle_q_host, model.spring_indices_host, model.spring_rest_host,
                   model.spring_stiffness_host, model.spring_damping_host,
                   model.particle_inv_mass.numpy().astype(np.float64))


def _proportional_ratio(ks, kd) -> float | None:
    """``kd / ks`` when every spring shares it (then ``D = ratio S`` at rest), else None."""
    ks = np.asarray(ks, dtype=np.float64)
    kd = np.asarray(kd, dtype=np.float64)
    if ks.size == 0 or np.any(ks <= 0.0):
        return None
    ratio = kd / ks
    return float(ratio[0]) if np.allclose(ratio, ratio[0], rtol=1e-12, atol=0.0) else None


def predict_model_dt(model: Model, methods=NAMES, *, tol=DEFAULT_TOL, max_iterations=MAX_ITERATIONS,
                     seed=SEED) -> Prediction:
    """Largest stable dt of each method for ``model`` linearised at its start positions.

    The start positions should be at rest (a jelly as built): the spring Jacobians are taken there,
    and gravity, terrain and contact are left out (a free jelly). The analysis is float64 whatever
    the model's precision; the model's host arrays are read, and no kernel runs.

    Args:
        model: the model.
        methods: integrator names (:data:`.methods.NAMES`).
        tol: relative change of the largest Ritz value over :data:`CHECK_EVERY` iterations below
            which (with each method's step settled to :data:`DEFAULT_DT_TOL`) the iteration stops.
        max_iterations: Lanczos iterations at most (also capped by :data:`MEMORY_BUDGET`).
        seed: seed of the random start vector.

    Returns:
        A :class:`Prediction`; ``dt`` as :func:`.stability_analysis.max_stable_dt` (``inf`` for
        implicit, ``0.0`` where an undamped mode makes a method unstable at every step).
    """
    return predict_operator_dt(SpringOperator.of_model(model), tuple(methods), tol=tol, max_iterations=max_iterations,
                               seed=seed)


def predict_operator_dt(op: SpringOperator, methods=NAMES, *, tol=DEFAULT_TOL, dt_tol=DEFAULT_DT_TOL,
                        min_iterations=MIN_ITERATIONS, max_iterations=MAX_ITERATIONS, check_every=CHECK_EVERY,
                        seed=SEED) -> Prediction:
    """:func:`predict_model_dt` for the springs of a :class:`SpringOperator`.

    The iteration stops when, over ``check_every`` iterations (from ``min_iterations`` on), the
    largest Ritz value moves by less than ``tol`` and each method's step estimate by less than
    ``dt_tol`` (relative), see :func:`_estimates`.
    """
    n = 3 * op.n
    ratio = _proportional_ratio(op.ks, op.kd)
    per_vector = 8 * n
    k_max = int(max(min_iterations, min(max_iterations, MEMORY_BUDGET // max(per_vector, 1))))
    k_max = min(k_max, 3 * int(np.count_nonzero(op.free)))
    if k_max == 0 or op.a.size == 0:
        return Prediction({m: math.inf for m in methods}, 0, True, ratio is not None, 0.0)  # nothing to vibrate

    rng = np.random.default_rng(seed)
    mask = np.tile(op.free, 3).astype(np.float64)  # component-major, as SpringOperator's vectors
    V = np.zeros((k_max + 1, n))
    # Projections V^T St V and V^T Dt V, filled a column per iteration: column j is V[:j+1] . (St v_j),
    # which is also the first Gram-Schmidt pass of the Lanczos expansion by St v_j.
    PS = np.zeros((k_max, k_max))
    PD = None if ratio is not None else np.zeros((k_max, k_max))
    v = rng.standard_normal(n) * mask
    V[0] = v / _norm(v)
    k = 0
    converged = False
    last = None
    for j in range(k_max):
        sv, dv = op.apply(V[j], damping=PD is not None)
        basis = V[: j + 1]
        PS[: j + 1, j] = _times(basis, sv)
        if PD is not None:
            PD[: j + 1, j] = _times(basis, dv)
        # Expand by St (Lanczos); without proportional damping every other step by Dt, so the basis
        # also holds the directions the dampers couple.
        if PD is not None and j % 2:
            w, h = dv, PD[: j + 1, j].copy()
        else:
            w, h = sv, PS[: j + 1, j].copy()
        size = _norm(w)
        w = w - _combine(basis, h)
        # Full reorthogonalisation: a second pass when the first cancelled most of w (the
        # Daniel-Gragg-Kaufman-Stewart test; "twice is enough").
        if _norm(w) < 0.7071 * size:
            w -= _combine(basis, _times(basis, w))
        k = j + 1
        norm = _norm(w)
        if norm <= 1e-12 * max(size, 1e-300):  # an invariant subspace: the Ritz values are exact
            converged = True
            break
        V[j + 1] = w / norm
        if k >= min_iterations and k % check_every == 0:
            now = _estimates(_symmetric(PS, k), ratio, PD, k, methods)
            if last is not None and all(abs(a - b) <= t * abs(a) or a == b for a, b, t in
                                        zip(now, last, (tol,) + (dt_tol,) * (len(now) - 1))):
                converged = True
                break
            last = now
    T = _symmetric(PS, k)
    Dp = ratio * T if ratio is not None else _symmetric(PD, k)
    # The projected system in stability_analysis's convention (K = df/dx = -S, C = -D, unit masses).
    Kr, Cr, _ = sa._reduced(-T, -Dp, 1.0)
    lam = np.linalg.eigvals(sa._first_order(Kr, Cr)) if Kr.size else np.zeros(0, complex)
    dt = {m: sa._max_stable_dt_reduced(m, Kr, Cr, 1e-4, 1e-9, sa._ZERO_TOL, lam=lam) for m in methods}
    top = float(np.linalg.eigvalsh(T)[-1]) if k else 0.0
    return Prediction(dt, k, converged, ratio is not None, math.sqrt(max(top, 0.0)))


# Products with the basis are einsum loops, not BLAS: they are memory-bound matrix-vector products,
# which one thread does at full bandwidth, and a threaded BLAS on a busy machine (its threads
# competing for cores) made them ten times slower.


def _times(basis, x):
    """``basis @ x``."""
    return np.einsum("ij,j->i", basis, x)


def _combine(basis, h):
    """``basis.T @ h``."""
    return np.einsum("ij,i->j", basis, h)


def _norm(x):
    return math.sqrt(np.einsum("i,i->", x, x))


def _symmetric(P, k):
    """The leading ``k x k`` block of a projection whose upper triangle is filled, made symmetric."""
    U = np.triu(P[:k, :k])
    return U + np.triu(U, 1).T


def _estimates(T, ratio, PD, k, methods):
    """(largest Ritz value, each method's step on the projected system): what convergence watches.

    Runge-Kutta steps are exact on the projected system; symplectic Euler's is its modal estimate
    (:func:`.stability_analysis._symplectic_modal_estimate`), which the bisection at the end refines.
    """
    Dp = ratio * T if ratio is not None else _symmetric(PD, k)
    Kr, Cr, _ = sa._reduced(-T, -Dp, 1.0)
    lam = np.linalg.eigvals(sa._first_order(Kr, Cr)) if Kr.size else np.zeros(0, complex)
    out = [float(np.linalg.eigvalsh(T)[-1])]
    for m in methods:
        if method(m).partitioned:
            out.append(sa._symplectic_modal_estimate(Kr, Cr) if Kr.size else math.inf)
        else:
            out.append(sa._max_stable_dt_reduced(m, Kr, Cr, 1e-4, 1e-9, sa._ZERO_TOL, lam=lam))
    return out


# ---------------------------------------------------------------------------------------------
# A scene's jelly, free


def free_jelly(jelly: dict, ks=None, undamped=False, max_n=None) -> dict:
    """A validated-jelly dict of ``jelly`` (spacing, particle mass, springs), free and at rest.

    Args:
        jelly: a validated scene jelly (``particle_mass`` filled in).
        ks: when given, every spring type's stiffness [N/m].
        undamped: set every ``kd`` to 0.
        max_n: particles per axis at most, at the jelly's spacing (None: the jelly's own resolution).
    """
    res = jelly["resolution"]
    small = [n if max_n is None else min(n, max_n) for n in res]
    spacing = [s / (n - 1) if n > 1 else 0.0 for s, n in zip(jelly["size"], res)]
    size = [sp * (n - 1) if n > 1 else 0.0 for sp, n in zip(spacing, small)]
    springs = {}
    for name, p in jelly["springs"].items():
        springs[name] = {"ks": float(ks) if ks is not None else p["ks"], "kd": 0.0 if undamped else p.get("kd", 0.0)}
    return {"resolution": small, "size": size, "particle_mass": jelly["particle_mass"], "springs": springs}


def free_jelly_model(jelly_small: dict, device, precision):
    """Model of the free jelly: no gravity, no terrain."""

    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    size = [s if s > 0 else 1.0 for s in jelly_small["size"]]  # an axis of one particle has no extent
    b.add_jelly(jelly_small["resolution"], size, jelly_small["particle_mass"], jelly_small["springs"])
    return b.finalize(device, precision)


def jelly_builder(jelly: dict, pinned=()) -> ModelBuilder:
    """A builder holding a validated scene jelly alone, free (no gravity) and at rest.

    A box jelly is its lattice; a mesh jelly is its voxelised lattice (``core/voxelize.py``, the
    lattice validation made), with its own particle mass. ``pinned``: particle indices given mass 0
    (held fixed, as a scene's pins hold them).
    """
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    at_rest = {**jelly, "center": [0.0, 0.0, 0.0], "rotation": {"axis": [0.0, 1.0, 0.0], "degrees": 0.0},
               "velocity": [0.0, 0.0, 0.0], "angular_velocity": [0.0, 0.0, 0.0]}
    at_rest.pop("initial_scale", None)  # the start is stretched, the rest pose is not
    if "mesh" in jelly:
        from .voxelize import add_mesh_jelly  # noqa: PLC0415 - the mesh extra

        add_mesh_jelly(b, at_rest)
    else:
        b.add_jelly(at_rest["resolution"], at_rest["size"], at_rest["particle_mass"], at_rest["springs"])
    if len(pinned):
        b._mass[0][np.asarray(pinned, dtype=np.int64)] = 0.0
    return b


def jelly_operator(jelly: dict, pinned=()) -> SpringOperator:
    """The :class:`SpringOperator` of a validated scene jelly, free and at rest (no model is built;
    see :func:`jelly_builder`)."""
    b = jelly_builder(jelly, pinned)
    mass = np.concatenate(b._mass)
    inv_mass = np.where(mass > 0.0, 1.0 / np.where(mass > 0.0, mass, 1.0), 0.0)
    if not b._pairs:
        return SpringOperator(np.concatenate(b._q), np.zeros((0, 2), dtype=np.int32), 0.0, 0.0, 0.0, inv_mass)
    return SpringOperator(np.concatenate(b._q), np.concatenate(b._pairs), np.concatenate(b._rest),
                          np.concatenate(b._ks), np.concatenate(b._kd), inv_mass)


def predict_jelly_dt(jelly: dict, methods=NAMES, device=None, max_n=None, *, pinned=(), **lanczos) -> Prediction:
    """:func:`predict_model_dt` for a validated scene jelly, free and at rest, in float64 on the host.

    ``max_n`` (box jellies): particles per axis at most, at the jelly's spacing. ``device`` is
    accepted for callers that name one; the analysis runs in NumPy. ``lanczos``: the iteration's
    settings (:func:`predict_operator_dt`).
    """
    del device
    if max_n is not None and "mesh" not in jelly:
        jelly = {**jelly, **free_jelly(jelly, max_n=max_n)}
    return predict_operator_dt(jelly_operator(jelly, pinned), tuple(methods), **lanczos)

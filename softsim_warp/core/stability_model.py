"""Largest stable step of a whole model, matrix-free on its device (Lanczos).

:mod:`.stability_analysis` linearises a jelly at rest, ``M dx'' = K dx + C dv``, and finds each
integrator's largest stable step from the dense eigenproblem. That costs ``(6N)^3`` and is limited
to a few hundred particles, yet the limit depends on the jelly's size: the stiffest modes of a
10x10x10 lattice are 18 % stiffer than those of a 4x4x4 one, because a small lattice is mostly
boundary. This module predicts the limit of the model itself, at any size:

1. The spring Jacobians at the model's start positions, ``S = -dK`` and ``D = -C`` per spring, come
   from the implicit integrator's own kernels (``eval_spring_jacobians`` with ``h = 1`` and the
   damping, then the stiffness, set to zero), and their products with a vector from its
   ``spring_mv``; nothing is assembled.
2. Lanczos with full reorthogonalisation on the mass-weighted ``St = M^-1/2 S M^-1/2`` (fixed
   particles, inverse mass 0, removed) builds an orthonormal Krylov basis ``V`` (when the springs'
   ``kd / ks`` differ, every other expansion uses ``Dt`` instead, so that the basis also holds the
   directions the dampers couple). Its extreme Ritz
   values converge first, at both ends of the spectrum, which is where the limiting modes are: the
   stiffest modes limit every explicit method, and for explicit Euler the softest underdamped ones
   can too. Iteration stops when, over ``CHECK_EVERY`` iterations, the largest Ritz value moves by
   less than ``tol`` (relative) and the smallest non-zero one by less than ``sqrt(tol)`` (it
   converges slowest, and limits explicit Euler only, through its damping rather than its size).
3. The damped system projected on ``V``, ``a'' = -V^T St V a - V^T Dt V a'``, is small (``k x k``,
   ``k`` the number of iterations) and goes through the dense analysis of
   :mod:`.stability_analysis` (deflation of free modes, per-eigenvalue limits, the symplectic step
   map). When every spring has the same ``kd / ks``, ``Dt = (kd/ks) St`` and the projection is exact
   in the Krylov space; otherwise ``V^T Dt V`` is the Rayleigh-Ritz approximation of the damping.

The basis costs ``2k`` vectors of ``3N`` float64 on the host (``3k`` without proportional
damping); :data:`MEMORY_BUDGET` caps ``k``, which limits the accuracy only for jellies of millions
of particles (the report says how many iterations ran and whether they converged).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from . import stability_analysis as sa
from ..kernels import implicit as ki
from .model import Model, ModelBuilder

MAX_ITERATIONS = 300
MIN_ITERATIONS = 30
CHECK_EVERY = 10
DEFAULT_TOL = 1.0e-4
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


class _Operator:
    """Products with the mass-weighted stiffness and damping Jacobians of a model at its start positions."""

    def __init__(self, model: Model):
        self.model = model
        device = model.device
        s = model.spring_count
        mat33 = wp.types.matrix((3, 3), model.scalar)
        n = model.particle_count
        zeros_s = wp.zeros(s, dtype=model.scalar, device=device)
        self.s_block = wp.zeros(s, dtype=mat33, device=device)
        self.d_block = wp.zeros(s, dtype=mat33, device=device)
        diag = wp.zeros(n, dtype=mat33, device=device)
        rhs = wp.zeros(n, dtype=model.vec3, device=device)
        one = model.scalar(1.0)
        # Blocks of one spring (kernels/implicit.py spring_jacobian): B = h kd d^d^T + h^2 S at h = 1.
        for blocks, stiffness, damping in ((self.s_block, model.spring_stiffness, zeros_s),
                                           (self.d_block, zeros_s, model.spring_damping)):
            wp.launch(model.kernels.eval_spring_jacobians, dim=s,
                      inputs=[one, model.scalar(0.0), model.spring_indices, model.spring_rest_length, stiffness, damping,
                              model.particle_q, rhs],
                      outputs=[blocks, diag, rhs], device=device)
        inv_mass = model.particle_inv_mass.numpy().astype(np.float64)
        self.free = inv_mass > 0.0
        # Mass-weighting of the free particles' dofs; fixed particles keep zero rows and columns.
        self.w = np.repeat(np.sqrt(inv_mass), 3)
        self.p = wp.zeros(n, dtype=model.vec3, device=device)
        self.y = wp.zeros(n, dtype=model.vec3, device=device)
        self.scalars = wp.zeros(ki.SCALAR_SLOTS, dtype=model.scalar, device=device)
        self.np_scalar = np.float64 if model.scalar == wp.float64 else np.float32

    def apply(self, blocks, v: np.ndarray) -> np.ndarray:
        """``M^-1/2 B M^-1/2 v`` for the assembled spring blocks ``B`` (flat ``(3N,)`` float64 vectors)."""
        model = self.model
        s = model.spring_count
        self.p.assign((self.w * v).astype(self.np_scalar).reshape(-1, 3))
        self.y.zero_()
        wp.launch(model.kernels.spring_mv, dim=(ki.tile_blocks(s), ki.TILE), block_dim=ki.TILE,
                  inputs=[s, ki.PAP, model.spring_indices, blocks, self.p], outputs=[self.y, self.scalars],
                  device=model.device)
        return self.w * self.y.numpy().astype(np.float64).reshape(-1)


def _proportional_ratio(model: Model) -> float | None:
    """``kd / ks`` when every spring shares it (then ``D = ratio S`` at rest), else None."""
    ks = np.asarray(model.spring_stiffness_host, dtype=np.float64)
    kd = np.asarray(model.spring_damping_host, dtype=np.float64)
    if ks.size == 0 or np.any(ks <= 0.0):
        return None
    ratio = kd / ks
    return float(ratio[0]) if np.allclose(ratio, ratio[0], rtol=1e-12, atol=0.0) else None


def predict_model_dt(model: Model, methods=sa.METHODS, *, tol=DEFAULT_TOL, max_iterations=MAX_ITERATIONS,
                     seed=SEED) -> Prediction:
    """Largest stable dt of each method for ``model`` linearised at its start positions.

    The start positions should be at rest (a jelly as built): the spring Jacobians are taken there,
    and gravity, terrain and contact are left out (a free jelly). Use a float64 model for accuracy.

    Args:
        model: the model (its spring list is made on first use).
        methods: integrator names (:data:`.stability_analysis.METHODS`).
        tol: relative change of the extreme Ritz values over :data:`CHECK_EVERY` iterations at which
            the iteration stops.
        max_iterations: Lanczos iterations at most (also capped by :data:`MEMORY_BUDGET`).
        seed: seed of the random start vector.

    Returns:
        A :class:`Prediction`; ``dt`` as :func:`.stability_analysis.max_stable_dt` (``inf`` for
        implicit, ``0.0`` where an undamped mode makes a method unstable at every step).
    """
    op = _Operator(model)
    n = 3 * model.particle_count
    ratio = _proportional_ratio(model)
    per_vector = 8 * n * (2 if ratio is not None else 3)
    k_max = int(max(MIN_ITERATIONS, min(max_iterations, MEMORY_BUDGET // max(per_vector, 1))))
    k_max = min(k_max, int(np.count_nonzero(np.repeat(op.free, 3))))
    if k_max == 0 or model.spring_count == 0:
        return Prediction({m: math.inf for m in methods}, 0, True, ratio is not None, 0.0)  # nothing to vibrate

    rng = np.random.default_rng(seed)
    mask = np.repeat(op.free, 3).astype(np.float64)
    V = np.zeros((k_max + 1, n))
    SV = np.zeros((k_max, n))
    DV = None if ratio is not None else np.zeros((k_max, n))
    v = rng.standard_normal(n) * mask
    V[0] = v / np.linalg.norm(v)
    k = 0
    converged = False
    last = None
    for j in range(k_max):
        SV[j] = op.apply(op.s_block, V[j]) * mask
        if DV is not None:
            DV[j] = op.apply(op.d_block, V[j]) * mask
        # Expand by St (Lanczos); without proportional damping every other step by Dt, so the basis
        # also holds the directions the dampers couple.
        w = (DV[j] if DV is not None and j % 2 else SV[j]).copy()
        for _ in range(2):  # full reorthogonalisation, twice ("twice is enough")
            w -= V[: j + 1].T @ (V[: j + 1] @ w)
        k = j + 1
        norm = np.linalg.norm(w)
        if norm <= 1e-12 * max(np.linalg.norm(SV[j]), 1e-300):  # an invariant subspace: the Ritz values are exact
            converged = True
            break
        V[j + 1] = w / norm
        if k >= MIN_ITERATIONS and k % CHECK_EVERY == 0:
            ends = _extreme_ritz(_projected(V, SV, k))
            if last is not None and all(abs(a - b) <= t * abs(a) for a, b, t in zip(ends, last, (tol, math.sqrt(tol)))):
                converged = True
                break
            last = ends
    T = _projected(V, SV, k)
    Dp = ratio * T if ratio is not None else _projected(V, DV, k)
    # The projected system in stability_analysis's convention (K = df/dx = -S, C = -D, unit masses).
    Kr, Cr, _ = sa._reduced(-T, -Dp, 1.0)
    lam = np.linalg.eigvals(sa._first_order(Kr, Cr)) if Kr.size else np.zeros(0, complex)
    dt = {m: sa._max_stable_dt_reduced(m, Kr, Cr, 1e-4, 1e-9, sa._ZERO_TOL, lam=lam) for m in methods}
    top = float(np.linalg.eigvalsh(T)[-1]) if k else 0.0
    return Prediction(dt, k, converged, ratio is not None, math.sqrt(max(top, 0.0)))


def _projected(V, AV, k):
    """``V^T A V`` over the first ``k`` basis vectors, symmetrised."""
    P = V[:k] @ AV[:k].T
    return 0.5 * (P + P.T)


def _extreme_ritz(T):
    """The largest Ritz value and the smallest one clearly above zero (free modes have zero)."""
    theta = np.linalg.eigvalsh(T)
    top = theta[-1]
    soft = theta[theta > 1e-6 * top]
    return (top, soft[0] if soft.size else top)


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


def predict_jelly_dt(jelly: dict, methods=sa.METHODS, device=None, max_n=None) -> Prediction:
    """:func:`predict_model_dt` for a validated scene jelly, free and at rest, in float64 on ``device``."""
    return predict_model_dt(free_jelly_model(free_jelly(jelly, max_n=max_n), device, "float64"), tuple(methods))

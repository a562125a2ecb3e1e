"""Linear stability analysis of the mass-spring jelly: the largest stable time step per integrator.

The jelly's equations of motion ``M x'' = f(x, v) + M g`` are linearised about a configuration at
rest, giving ``M dx'' = K dx + C dv`` with the stiffness Jacobian ``K = df/dx`` and the damping
Jacobian ``C = df/dv``. Gravity is constant and drops out. Written as a first-order system
``y' = A y`` with ``y = (dx, dv)`` and ``A = [[0, I], [M^-1 K, M^-1 C]]``, each integrator advances
``y`` by a linear map per step, and the step is stable when that map's spectral radius is <= 1:

* Runge-Kutta methods (``euler``, ``midpoint``, ``rk4``, ``implicit``) map ``y`` by ``R(hA)``, whose
  eigenvalues are ``R(h lambda)`` for the eigenvalues ``lambda`` of ``A``. The largest stable ``h``
  is found per eigenvalue, exactly, as the first root of ``|R(t e)|^2 = 1`` along the ray ``e`` of
  that eigenvalue.
* Symplectic (semi-implicit) Euler is a partitioned method and has no ``R(z)``: its step matrix
  ``S(h)`` is built explicitly and its spectral radius is found by bracketing and bisection in ``h``.

Modes that neither stretch nor damp any spring (rigid translations and rotations, plus mechanisms of
degenerate lattices) move in free flight, ``x'' = 0``, which every integrator reproduces exactly
(``R(0) = 1``). They are deflated before any eigenvalue is taken: numerically they form 2x2 Jordan
blocks at zero whose computed eigenvalues scatter by ``sqrt(eps) * |A|`` in random directions, which
would otherwise look like unstable modes.

Everything is dense NumPy: fine up to a few hundred particles (a 6x6x6 lattice is a 1296 x 1296
eigenproblem), which is what the analysis is for: predicting the step of a lattice resolution
before simulating it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from . import lattice
from .methods import NAMES
from .methods import method as method_of  # ``method`` is the argument naming a method in this module

# Relative size below which an eigenvalue (or its real part) is taken as exactly zero. Eigenvalues
# of a dense eigensolver are accurate to about eps * |A| in absolute terms, so the tolerance is
# relative to the largest eigenvalue magnitude, not to each eigenvalue's own magnitude.
_ZERO_TOL = 1e-9


# ---------------------------------------------------------------------------------------------
# Linearisation


def linearize(points, pairs, rest, ks, kd, masses):
    """Stiffness and damping Jacobians of the spring forces at a configuration at rest.

    The force on particle ``a`` of spring ``(a, b)`` is
    ``f_a = -ks (|d| - r) d^ - kd ((v_a - v_b) . d^) d^`` with ``d = x_a - x_b``, and ``b`` gets
    ``-f_a``. Its derivative with respect to ``x_a`` is the 3x3 block

    ``k = -ks [d^ d^T + (1 - r/|d|) (I - d^ d^T)]``,

    the first term from stretching along the spring and the second from rotating a spring under
    tension (it vanishes at rest length, so at the rest configuration ``k = -ks d^ d^T``). The
    derivative with respect to ``v_a`` is ``c = -kd d^ d^T``. The blocks enter ``K`` and ``C`` as
    ``+k`` at ``(a, a)`` and ``(b, b)`` and ``-k`` at ``(a, b)`` and ``(b, a)``, since ``f_b = -f_a``
    and ``f`` depends on ``x_a - x_b`` only.

    The particles are taken to be momentarily at rest (zero relative velocities): the damping force
    also depends on the positions through ``d^``, but that derivative is proportional to the
    relative velocity and vanishes there. This keeps both ``K`` and ``C`` symmetric.

    Args:
        points: ``(N, 3)`` particle positions [m] at which to linearise.
        pairs: ``(S, 2)`` particle indices of the springs.
        rest: ``(S,)`` rest lengths [m] (or a scalar).
        ks: ``(S,)`` spring stiffnesses [N/m] (or a scalar).
        kd: ``(S,)`` spring damping coefficients [N s/m] (or a scalar).
        masses: ``(N,)`` particle masses [kg] (or a scalar).

    Returns:
        ``(K, C, M_diag)``: the ``(3N, 3N)`` float64 Jacobians ``df/dx`` [N/m] and ``df/dv``
        [N s/m], with the coordinates of particle ``i`` at rows ``3i..3i+2``, and the ``(3N,)``
        diagonal of the mass matrix [kg].

    Raises:
        ValueError: if a spring has zero length (its direction, and so the force, is undefined) or
            a mass is not positive.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    n = points.shape[0]
    s = pairs.shape[0]
    rest = np.broadcast_to(np.asarray(rest, dtype=np.float64), (s,))
    ks = np.broadcast_to(np.asarray(ks, dtype=np.float64), (s,))
    kd = np.broadcast_to(np.asarray(kd, dtype=np.float64), (s,))
    masses = np.broadcast_to(np.asarray(masses, dtype=np.float64), (n,))
    if np.any(masses <= 0.0):
        raise ValueError("particle masses must be positive for the stability analysis")

    a, b = pairs[:, 0], pairs[:, 1]
    d = points[a] - points[b]
    length = np.linalg.norm(d, axis=1)
    if np.any(length <= 0.0):
        raise ValueError("a spring has zero length; its direction (and force) is undefined")
    dhat = d / length[:, None]
    outer = dhat[:, :, None] * dhat[:, None, :]  # (S, 3, 3) projector onto the spring axis
    transverse = np.eye(3) - outer  # projector onto the plane across the spring
    tension = (1.0 - rest / length)[:, None, None]
    k_block = -ks[:, None, None] * (outer + tension * transverse)
    c_block = -kd[:, None, None] * outer

    K = _assemble(n, a, b, k_block)
    C = _assemble(n, a, b, c_block)
    return K, C, np.repeat(masses, 3)


def _assemble(n, a, b, blocks):
    """Scatter per-spring 3x3 blocks into a dense ``(3N, 3N)`` matrix with the +k/-k pattern."""
    out = np.zeros((n, 3, n, 3))
    # np.add.at accumulates repeated indices (a particle with several springs); with the advanced
    # indices split by a slice, the spring axis comes first, matching the (S, 3, 3) blocks.
    full = slice(None)
    np.add.at(out, (a, full, a, full), blocks)
    np.add.at(out, (b, full, b, full), blocks)
    np.add.at(out, (a, full, b, full), -blocks)
    np.add.at(out, (b, full, a, full), -blocks)
    return out.reshape(3 * n, 3 * n)


def _mass_diag(masses, size):
    """Per-coordinate masses ``(3N,)`` from per-particle ``(N,)``, per-coordinate or scalar masses."""
    m = np.asarray(masses, dtype=np.float64).ravel()
    if m.size == 1:
        return np.full(size, m[0])
    if m.size * 3 == size:
        return np.repeat(m, 3)
    if m.size == size:
        return m
    raise ValueError(f"masses has {m.size} entries; expected 1, {size // 3} or {size}")


def system_matrix(K, C, masses):
    """The ``(6N, 6N)`` matrix ``A = [[0, I], [M^-1 K, M^-1 C]]`` of the linearised system.

    Args:
        K: ``(3N, 3N)`` stiffness Jacobian.
        C: ``(3N, 3N)`` damping Jacobian.
        masses: particle masses: ``(N,)``, ``(3N,)`` (``M_diag``) or a scalar.

    Returns:
        ``(6N, 6N)`` float64 matrix acting on ``y = (dx, dv)``.
    """
    K = np.asarray(K, dtype=np.float64)
    C = np.asarray(C, dtype=np.float64)
    m = _mass_diag(masses, K.shape[0])
    n3 = K.shape[0]
    A = np.zeros((2 * n3, 2 * n3))
    A[:n3, n3:] = np.eye(n3)
    A[n3:, :n3] = K / m[:, None]
    A[n3:, n3:] = C / m[:, None]
    return A


def _reduced(K, C, masses, null_tol=_ZERO_TOL):
    """Mass-weighted Jacobians with the free (zero-stiffness, zero-damping) modes removed.

    In coordinates ``q = M^(1/2) x`` the system is ``q'' = Kt q + Ct q'`` with symmetric
    ``Kt = M^-1/2 K M^-1/2`` and ``Ct`` likewise. The common null space ``Z`` of ``Kt`` and ``Ct``
    is invariant and, by symmetry, so is its orthogonal complement ``Q``; the dynamics split into
    free flight on ``Z`` and ``a'' = Q^T Kt Q a + Q^T Ct Q a'`` on ``Q``. All integrators are linear
    and act on ``x`` and ``v`` alike, so the same split holds for their step maps.

    Returns:
        ``(Kr, Cr, n_free)``: the reduced mass-weighted Jacobians and the number of free modes.
    """
    K = np.asarray(K, dtype=np.float64)
    C = np.asarray(C, dtype=np.float64)
    m = _mass_diag(masses, K.shape[0])
    w = 1.0 / np.sqrt(m)
    Kt = K * w[:, None] * w[None, :]
    Ct = C * w[:, None] * w[None, :]
    if Kt.size == 0:
        return Kt, Ct, 0
    # Null space of Kt from its eigenvectors (eigenvalues accurate to eps * |Kt|, so a relative
    # threshold separates the exact null space from soft but real modes) ...
    k_eig, V = np.linalg.eigh(0.5 * (Kt + Kt.T))
    k_scale = float(np.max(np.abs(k_eig)))
    k_null = np.abs(k_eig) <= null_tol * k_scale
    Z = V[:, k_null]
    blocks = [V[:, ~k_null]]
    if Z.shape[1]:
        # ... then the part of it that the dampers do not touch either: the null space of the
        # (tall, few-column) Ct Z, from its SVD.
        c_scale = float(np.max(np.abs(np.linalg.eigvalsh(0.5 * (Ct + Ct.T)))))
        _, sigma, wt = np.linalg.svd(Ct @ Z)
        damped = np.zeros(Z.shape[1], dtype=bool)
        damped[: sigma.size] = sigma > null_tol * c_scale
        if c_scale == 0.0:
            damped[:] = False
        blocks.append(Z @ wt[damped].T)
    Q = np.hstack(blocks)
    Kr = Q.T @ Kt @ Q
    Cr = Q.T @ Ct @ Q
    # Re-symmetrise: the projection is symmetric in exact arithmetic only.
    Kr = 0.5 * (Kr + Kr.T)
    Cr = 0.5 * (Cr + Cr.T)
    return Kr, Cr, int(K.shape[0] - Q.shape[1])


def _first_order(Kr, Cr):
    """``[[0, I], [Kr, Cr]]`` for already mass-weighted Jacobians."""
    n = Kr.shape[0]
    A = np.zeros((2 * n, 2 * n))
    A[:n, n:] = np.eye(n)
    A[n:, :n] = Kr
    A[n:, n:] = Cr
    return A


def system_eigenvalues(K, C, masses, deflate=True):
    """Eigenvalues ``lambda`` of ``A = [[0, I], [M^-1 K, M^-1 C]]``.

    Args:
        K: ``(3N, 3N)`` stiffness Jacobian.
        C: ``(3N, 3N)`` damping Jacobian.
        masses: particle masses: ``(N,)``, ``(3N,)`` or a scalar.
        deflate: report the free modes (rigid motions: vectors in the null space of both ``K`` and
            ``C``) as exact zeros, two per mode, and take the eigenvalues of the rest only. Without
            it the dense eigensolver sees their 2x2 Jordan blocks and scatters them by about
            ``sqrt(eps) * |A|``.

    Returns:
        ``(6N,)`` complex eigenvalues [1/s], sorted by real then imaginary part. Oscillatory modes
        come in conjugate pairs ``-zeta w +- i w sqrt(1 - zeta^2)``.
    """
    if not deflate:
        return np.sort_complex(np.linalg.eigvals(system_matrix(K, C, masses)))
    Kr, Cr, n_free = _reduced(K, C, masses)
    lam = np.linalg.eigvals(_first_order(Kr, Cr)) if Kr.size else np.zeros(0, complex)
    return np.sort_complex(np.concatenate([np.zeros(2 * n_free, complex), lam]))


# ---------------------------------------------------------------------------------------------
# Stability functions and step maps


def stability_function(method):
    """The stability function ``R(z)`` of a Runge-Kutta method, as a vectorised callable.

    One step of the method on ``y' = lambda y`` gives ``y_{n+1} = R(h lambda) y_n``.

    Args:
        method: ``"euler"`` (``1 + z``), ``"midpoint"`` (``1 + z + z^2/2``), ``"rk4"``
            (``1 + z + z^2/2 + z^3/6 + z^4/24``) or ``"implicit"`` (backward Euler, ``1/(1 - z)``).

    Returns:
        Callable mapping complex array ``z`` to ``R(z)``.

    Raises:
        ValueError: for ``"symplectic"`` (a partitioned method: it treats ``x`` and ``v``
            differently, so its step is not a function of ``hA``; see :func:`symplectic_step_matrix`)
            or an unknown method.
    """
    if not method_of(method).explicit:
        return lambda z: 1.0 / (1.0 - np.asarray(z, dtype=complex))
    coeffs = _polynomial(method)
    return lambda z: np.polynomial.polynomial.polyval(np.asarray(z, dtype=complex), coeffs)


def _polynomial(name):
    """``R(z)``'s coefficients (ascending powers) of an explicit Runge-Kutta method, from its tableau.

    Raises:
        ValueError: for an unknown method, or a partitioned one (no ``R(z)``).
    """
    m = method_of(name)
    if m.partitioned:
        raise ValueError(f"{m.label} is partitioned and has no R(z); use symplectic_step_matrix")
    return np.array(m.stability_polynomial)


def _symplectic_step(Kw, Cw, h):
    """Step matrix of symplectic Euler for ``x'' = Kw x + Cw x'`` (``Kw``, ``Cw`` include ``M^-1``).

    ``v' = v + h (Kw x + Cw v)`` and ``x' = x + h v'`` give, on ``y = (x, v)``,
    ``S = [[I + h^2 Kw, h (I + h Cw)], [h Kw, I + h Cw]]``.
    """
    n = Kw.shape[0]
    eye = np.eye(n)
    vel = h * Kw  # contribution of x to v'
    damp = eye + h * Cw  # contribution of v to v'
    S = np.empty((2 * n, 2 * n))
    S[n:, :n] = vel
    S[n:, n:] = damp
    S[:n, :n] = eye + h * vel  # x' = x + h v'
    S[:n, n:] = h * damp
    return S


def symplectic_step_matrix(K, C, masses, h):
    """The ``(6N, 6N)`` matrix ``S(h)`` of one symplectic Euler step on the linearised system.

    From ``v_{n+1} = v_n + h M^-1 (K x_n + C v_n)`` and ``x_{n+1} = x_n + h v_{n+1}``:
    ``S = [[I + h^2 M^-1 K, h (I + h M^-1 C)], [h M^-1 K, I + h M^-1 C]]`` on ``y = (x, v)``.

    Args:
        K: ``(3N, 3N)`` stiffness Jacobian.
        C: ``(3N, 3N)`` damping Jacobian.
        masses: particle masses: ``(N,)``, ``(3N,)`` or a scalar.
        h: time step [s].

    Returns:
        ``(6N, 6N)`` float64 step matrix.
    """
    K = np.asarray(K, dtype=np.float64)
    m = _mass_diag(masses, K.shape[0])
    return _symplectic_step(K / m[:, None], np.asarray(C, dtype=np.float64) / m[:, None], float(h))


def _spectral_radius(M):
    return float(np.max(np.abs(np.linalg.eigvals(M)))) if M.size else 0.0


def step_spectral_radius(method, h, K, C, masses):
    """Spectral radius of one step of ``method`` with step ``h`` on the linearised system.

    Free (rigid) modes contribute exactly 1. A value above 1 means some mode grows every step.

    Args:
        method: one of :data:`.methods.NAMES`.
        h: time step [s].
        K: ``(3N, 3N)`` stiffness Jacobian.
        C: ``(3N, 3N)`` damping Jacobian.
        masses: particle masses: ``(N,)``, ``(3N,)`` or a scalar.

    Returns:
        ``max |eig(step map)|``.
    """
    Kr, Cr, n_free = _reduced(K, C, masses)
    base = 1.0 if n_free else 0.0
    if method_of(method).partitioned:
        return max(base, _spectral_radius(_symplectic_step(Kr, Cr, float(h))))
    lam = np.linalg.eigvals(_first_order(Kr, Cr)) if Kr.size else np.zeros(0, complex)
    R = stability_function(method)
    return max([base] + list(np.abs(R(h * lam))))


# ---------------------------------------------------------------------------------------------
# Largest stable step


def _clean_eigenvalues(lam, zero_tol):
    """Drop eigenvalues that are zero to rounding and snap real parts that are zero to rounding.

    Returns:
        ``(lam, scale)``: the cleaned nonzero eigenvalues and ``max |lambda|``.
    """
    lam = np.asarray(lam, dtype=complex).ravel()
    scale = float(np.max(np.abs(lam))) if lam.size else 0.0
    if scale == 0.0:
        return np.zeros(0, complex), 0.0
    lam = lam[np.abs(lam) > zero_tol * scale]
    # An undamped mode's eigenvalue comes back with a real part of +-eps * |A|; its sign would decide
    # between "unstable for every h" and "stable" for euler/midpoint, so snap it to exactly zero.
    re = np.where(np.abs(lam.real) <= zero_tol * scale, 0.0, lam.real)
    lam = re + 1j * lam.imag
    # Conjugates share |R(h lambda)| (R has real coefficients): keep one of each pair.
    return lam[lam.imag >= 0.0], scale


def _rk_first_exit(coeffs, lam):
    """Largest ``h`` such that ``|R(s lambda)| <= 1`` for all ``0 < s <= h``, for polynomial ``R``.

    Along the ray ``z = t e`` (``e = lambda/|lambda|``), ``q(t) = |R(t e)|^2 - 1`` is a real
    polynomial with ``q(0) = 0``. Its lowest nonzero coefficient decides stability for small ``t``
    (positive: unstable at once, e.g. euler on an undamped mode, ``q = t^2``); otherwise the first
    positive root where ``q`` turns positive is the exit from the stability region.
    """
    mag = abs(lam)
    e = lam / mag
    p = coeffs * e ** np.arange(coeffs.size)
    q = np.convolve(p, np.conj(p)).real  # ascending coefficients of |R(t e)|^2
    q[0] -= 1.0
    # Coefficients are sums of O(1) terms that cancel exactly for e = +-i; 1e-12 absorbs rounding.
    nonzero = np.flatnonzero(np.abs(q) > 1e-12)
    if nonzero.size == 0:
        return math.inf
    low = nonzero[0]
    if q[low] > 0.0:
        return 0.0
    r = q[low:]  # q(t) / t^low, negative at t = 0+
    roots = np.roots(r[::-1])
    real = np.sort(roots.real[(np.abs(roots.imag) <= 1e-8 * np.maximum(1.0, np.abs(roots))) & (roots.real > 0.0)])
    for t in real:
        # A double root only touches zero; the exit is where q actually becomes positive.
        if np.polynomial.polynomial.polyval(t * (1.0 + 1e-6), r) > 0.0:
            return float(t) / mag
    return math.inf


def max_stable_dt_from_eigenvalues(method, eigenvalues, *, zero_tol=_ZERO_TOL):
    """Largest stable step of a Runge-Kutta method for a system with the given eigenvalues.

    For each eigenvalue the exit from the stability region along its ray is found exactly (a root of
    a polynomial), so no bisection is needed; the system's step is the smallest over its modes.
    Stability means ``|R(h lambda)| <= 1`` for every step in ``(0, h]``.

    Args:
        method: ``"euler"``, ``"midpoint"``, ``"rk4"`` or ``"implicit"``.
        eigenvalues: eigenvalues of ``A`` [1/s] (e.g. from :func:`system_eigenvalues`). Zeros (rigid
            modes) are ignored: ``|R(0)| = 1``.
        zero_tol: eigenvalues with ``|lambda|``, and real parts with ``|Re lambda|``, at most
            ``zero_tol * max|lambda|`` are treated as exactly zero.

    Returns:
        The step [s]. ``inf`` for ``implicit`` (A-stable) or when no mode limits the step. ``0.0`` when
        some mode is unstable for every ``h > 0``: ``euler`` and ``midpoint`` on an undamped
        oscillatory mode (``lambda = +-i w``; ``|1 + i h w| > 1`` for all ``h > 0`` — the method
        injects energy however small the step), or any explicit method when the linearised system
        itself has a growing mode (``Re lambda > 0``).
    """
    if not method_of(method).explicit:
        # Backward Euler: |1/(1 - z)| <= 1 on the whole left half plane, for every h.
        return math.inf
    coeffs = _polynomial(method)  # raises with the reason (partitioned or unknown)
    lam, _ = _clean_eigenvalues(eigenvalues, zero_tol)
    if lam.size == 0:
        return math.inf
    if np.any(lam.real > 0.0):
        return 0.0
    # Identical eigenvalues (lattice symmetry) give identical exits: solve each distinct one once.
    distinct = np.unique(np.round(lam / np.max(np.abs(lam)), 12))
    best = math.inf
    for z in distinct:
        h = _rk_first_exit(coeffs, complex(z)) / np.max(np.abs(lam))
        best = min(best, h)
        if best == 0.0:
            break
    return float(best)


def _symplectic_modal_estimate(Kr, Cr):
    """Symplectic Euler's step bound if damping did not couple the undamped modes.

    For one mode ``x'' = -w^2 x - c x'`` the step matrix has ``det = 1 - hc`` and
    ``trace = 2 - hc - h^2 w^2``; both eigenvalues stay in the unit disc iff ``hc <= 2`` and
    ``h^2 w^2 <= 4 - 2hc``, i.e. ``h <= (sqrt(c^2 + 4 w^2) - c) / w^2`` (which implies ``hc <= 2``).
    """
    w2, phi = np.linalg.eigh(-Kr)
    c = np.einsum("ij,ij->j", phi, -Cr @ phi)  # modal damping, the diagonal of phi^T (-Cr) phi
    with np.errstate(divide="ignore", invalid="ignore"):
        undamped_bound = (np.sqrt(c * c + 4.0 * np.maximum(w2, 0.0)) - c) / w2
        h = np.where(w2 > 0.0, undamped_bound, np.where(c > 0.0, 2.0 / c, np.inf))
    return float(np.min(h)) if h.size else math.inf


def _symplectic_max_dt(Kr, Cr, rtol, growth_tol, zero_tol):
    """Bracket and bisect the largest ``h`` with ``rho(S(h)) <= 1 + growth_tol``."""
    if Kr.size == 0:
        return math.inf
    lam, scale = _clean_eigenvalues(np.linalg.eigvals(_first_order(Kr, Cr)), zero_tol)
    if lam.size == 0:
        return math.inf
    if np.any(lam.real > 0.0):
        return 0.0  # the exact solution grows; no step keeps it bounded

    def stable(h):
        return _spectral_radius(_symplectic_step(Kr, Cr, h)) <= 1.0 + growth_tol

    # Bracket around the modal estimate, which is exact when C is diagonal in K's modes
    # (proportional damping) and usually within a few percent otherwise; each failed side widens.
    h_est = _symplectic_modal_estimate(Kr, Cr)
    if not math.isfinite(h_est) or h_est <= 0.0:
        h_est = 1.0 / scale
    width = 1e-3
    lo = h_est * (1.0 - width)
    while not stable(lo):
        width = min(8.0 * width, 0.5)
        lo *= 1.0 - width
        if lo < 1e-12 / scale:
            return 0.0
    width = 1e-3
    hi = h_est * (1.0 + width)
    while stable(hi):
        lo = hi
        width = min(8.0 * width, 1.0)
        hi *= 1.0 + width
        if hi > 1e12 / scale:
            return math.inf
    # The stable set is an interval (0, h*] (per mode it is h^2 w^2 <= 4 - 2 h c), so bisection on
    # the bracket [stable lo, unstable hi] converges to its end.
    while hi - lo > rtol * lo:
        mid = 0.5 * (lo + hi)
        if stable(mid):
            lo = mid
        else:
            hi = mid
    return float(lo)


def max_stable_dt(method, K, C, masses, *, rtol=1e-4, growth_tol=1e-9, zero_tol=_ZERO_TOL):
    """Largest time step for which ``method`` does not amplify any mode of the linearised system.

    Args:
        method: one of :data:`.methods.NAMES`.
        K: ``(3N, 3N)`` stiffness Jacobian (from :func:`linearize`).
        C: ``(3N, 3N)`` damping Jacobian.
        masses: particle masses: ``(N,)``, ``(3N,)`` or a scalar.
        rtol: relative precision of the bisection in ``h`` (``symplectic`` only; the Runge-Kutta
            methods are solved exactly per eigenvalue).
        growth_tol: ``symplectic`` counts as stable while ``rho(S(h)) <= 1 + growth_tol``; on an
            undamped mode ``rho`` is exactly 1 up to the bound, so this only absorbs rounding.
        zero_tol: relative tolerance below which eigenvalues and their real parts count as zero
            (see :func:`max_stable_dt_from_eigenvalues`), and free modes are detected.

    Returns:
        The step [s]: ``inf`` for ``implicit``; ``0.0`` for ``euler``/``midpoint`` when an oscillatory
        mode is undamped (unstable for every ``h > 0``), or for any method but ``implicit`` when the
        linearisation has a growing mode. Rigid modes never limit the step.
    """
    if not method_of(method).explicit:
        return math.inf
    Kr, Cr, _ = _reduced(K, C, masses, zero_tol)
    return _max_stable_dt_reduced(method, Kr, Cr, rtol, growth_tol, zero_tol)


def _max_stable_dt_reduced(method, Kr, Cr, rtol, growth_tol, zero_tol, lam=None):
    if not method_of(method).explicit:
        return math.inf
    if method_of(method).partitioned:
        return _symplectic_max_dt(Kr, Cr, rtol, growth_tol, zero_tol)
    if lam is None:
        lam = np.linalg.eigvals(_first_order(Kr, Cr)) if Kr.size else np.zeros(0, complex)
    return max_stable_dt_from_eigenvalues(method, lam, zero_tol=zero_tol)


# ---------------------------------------------------------------------------------------------
# Lattices


def _per_type(value, name):
    """Per-spring-type values (structural, shear, bending) from a scalar, 3-sequence or mapping."""
    if isinstance(value, Mapping):
        out = []
        for t, type_name in enumerate(lattice.SPRING_TYPE_NAMES):
            if type_name in value:
                out.append(float(value[type_name]))
            elif t in value:
                out.append(float(value[t]))
            else:
                raise ValueError(f"{name} has no value for {type_name!r} springs (keys: {sorted(value, key=str)})")
        return np.array(out)
    arr = np.asarray(value, dtype=np.float64).ravel()
    if arr.size == 1:
        return np.full(3, arr[0])
    if arr.size == 3:
        return arr
    raise ValueError(f"{name} must be a scalar, 3 values (structural, shear, bending) or a mapping")


def lattice_jacobians(shape, size, particle_mass, ks, kd):
    """Linearise a jelly lattice at rest.

    Args:
        shape: particles per axis ``(nx, ny, nz)``.
        size: edge lengths ``(sx, sy, sz)`` [m], or one length for a cube.
        particle_mass: mass of each particle [kg] (scalar or ``(N,)``).
        ks: spring stiffness [N/m]: scalar, ``(structural, shear, bending)`` or a mapping keyed by
            type name (``"structural"``, ``"shear"``, ``"bending"``) or type number.
        kd: spring damping [N s/m], given like ``ks``.

    Returns:
        ``(K, C, M_diag)`` as from :func:`linearize`.
    """
    shape = tuple(int(n) for n in shape)
    size = np.broadcast_to(np.asarray(size, dtype=np.float64), (3,))
    points = lattice.lattice_points(shape, size)
    pairs, types = lattice.lattice_springs(shape)
    rest = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    return linearize(
        points, pairs, rest, _per_type(ks, "ks")[types], _per_type(kd, "kd")[types], particle_mass
    )


def predict_lattice_dt(shape, size, particle_mass, ks, kd, methods=NAMES, *, rtol=1e-4):
    """Largest stable time step of each integrator for a jelly lattice, linearised at rest.

    Args:
        shape: particles per axis ``(nx, ny, nz)``.
        size: edge lengths ``(sx, sy, sz)`` [m], or one length for a cube.
        particle_mass: mass of each particle [kg] (scalar or ``(N,)``).
        ks: spring stiffness [N/m]: scalar, ``(structural, shear, bending)`` or a mapping keyed by
            type name or type number.
        kd: spring damping [N s/m], given like ``ks``.
        methods: integrator names (see :data:`.methods.NAMES`).
        rtol: relative precision of the symplectic bisection.

    Returns:
        ``{method: dt}`` [s]; see :func:`max_stable_dt` for ``0.0`` and ``inf``.
    """
    K, C, m = lattice_jacobians(shape, size, particle_mass, ks, kd)
    # Deflate and take the eigenvalues once; every method reuses them.
    Kr, Cr, _ = _reduced(K, C, m)
    lam = np.linalg.eigvals(_first_order(Kr, Cr)) if Kr.size else np.zeros(0, complex)
    return {
        method: _max_stable_dt_reduced(method, Kr, Cr, rtol, 1e-9, _ZERO_TOL, lam=lam) for method in methods
    }


# ---------------------------------------------------------------------------------------------
# Plotting


def stability_region_boundary(method, n=400):
    """Points of the curve ``|R(z)| = 1`` bounding a Runge-Kutta method's stability region.

    For a polynomial ``R`` of degree ``p`` the curve is traced by following one root of
    ``R(z) = exp(i theta)`` as ``theta`` runs over ``[0, 2 pi p)``: the boundary wraps ``p`` times
    around the unit circle under ``R`` (the region holds all ``p`` zeros of ``R``), so a single
    continued root visits the whole closed curve, in order, ready for ``plt.plot``.

    Args:
        method: ``"euler"``, ``"midpoint"``, ``"rk4"`` or ``"implicit"`` (the circle
            ``|1 - z| = 1``; its stability region is the outside).
        n: number of points.

    Returns:
        ``(n,)`` complex points ``z = h lambda`` on the boundary, starting at ``z = 0``.
    """
    if not method_of(method).explicit:
        theta = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
        return 1.0 - np.exp(1j * theta)
    coeffs = _polynomial(method)  # raises with the reason (partitioned or unknown)
    p = coeffs.size - 1
    # Follow the root on a finer grid than requested so consecutive roots are unambiguous.
    fine = max(n, 256 * p)
    theta = np.linspace(0.0, 2.0 * np.pi * p, fine, endpoint=False)
    path = np.empty(fine, dtype=complex)
    z = 0.0 + 0.0j
    for i, th in enumerate(theta):
        c = coeffs.astype(complex)
        c[0] -= np.exp(1j * th)
        roots = np.roots(c[::-1])
        z = roots[np.argmin(np.abs(roots - z))]
        path[i] = z
    idx = np.linspace(0, fine, n, endpoint=False).astype(int)
    return path[idx]

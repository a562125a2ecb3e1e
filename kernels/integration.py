"""Integrator stages: explicit Runge-Kutta stages driven by a per-world tableau, and symplectic Euler.

Every explicit method here is written as stages of the first-order system y = (x, v), y' = (v, a):
stage s evaluates k_s = (v_s, a_s) at y_s, adds b_s k_s to an accumulator and forms the next stage
state y_{s+1} = y_n + h c_{s+1} k_s; the last stage writes y_{n+1} = y_n + h sum_s b_s k_s. The
tableau lives in arrays indexed by world, so one launch advances copies that use different methods
(the side-by-side comparison) and a single run is the one-world case.

The stage update is written once, in :func:`_stage_values_through`: ``stage_values`` reads and
writes through Warp's indexing (any array), ``stage_values_direct`` through the data pointers of
contiguous arrays (the fused lattice stage). Both are the same arithmetic.

Everything here is generic over float32 and float64 (kernels/precision.py), except the native
accessors, which are declared once per precision as overloads of one name.
"""

import warp as wp

from .precision import Float, both_precisions, vec3

wp.set_module_options({"enable_backward": False})


@wp.func
def acceleration(f: vec3, inv_mass: Float, gravity: vec3):
    """a = f/m + g; a particle of infinite mass (inv_mass 0) does not move."""
    if inv_mass == type(inv_mass)(0.0):
        return type(f)(type(inv_mass)(0.0))
    return f * inv_mass + gravity


# Element access through Warp's indexing: any array (a negative index wraps, the stride is read at
# run time).


@wp.func
def load_indexed(a: wp.array(dtype=vec3), i: int):
    return a[i]


@wp.func
def store_indexed(a: wp.array(dtype=vec3), i: int, value: vec3):
    a[i] = value


@wp.func
def int_indexed(a: wp.array(dtype=wp.int32), i: int):
    return a[i]


@wp.func
def scalar_indexed(a: wp.array(dtype=Float), i: int):
    return a[i]


@wp.func
def entry_indexed(a: wp.array2d(dtype=Float), j: int, k: int):
    return a[j, k]


@wp.func_native("return ((const int*)a.data)[i];")
def int_contiguous(a: wp.array(dtype=wp.int32), i: int) -> int:
    """``a[i]`` of a contiguous int32 array from its data pointer (see ``load_contiguous``)."""


# Element access through the data pointer of a contiguous array. Native snippets cannot be generic
# in their return type, so each is declared for float32 and for float64 under one name: Warp picks
# the overload from the argument types.
for _scalar, _ctype in ((wp.float32, "float"), (wp.float64, "double")):
    _vec3 = wp.types.vector(3, _scalar)

    @wp.func_native(
        f"const {_ctype}* t = (const {_ctype}*)a.data + 3 * i;\nreturn wp::vec_t<3, {_ctype}>(t[0], t[1], t[2]);"
    )
    def load_contiguous(a: wp.array(dtype=_vec3), i: int) -> _vec3:
        """``a[i]`` of a contiguous array, addressed as data + 3 i scalars.

        Warp's ``a[i]`` wraps a negative index and multiplies by the array's run-time 64-bit stride;
        here the element size is a constant, so a
        neighbour's address is the particle's plus an offset the compiler folds into the load, and
        the fused lattice stage's own loads and stores cost one address computation
        (docs/PERFORMANCE.md). Only for arrays the caller knows to be contiguous
        (``LatticeData.check_contiguous``).
        """

    @wp.func_native(f"{_ctype}* t = ({_ctype}*)a.data + 3 * i;\nt[0] = value[0]; t[1] = value[1]; t[2] = value[2];")
    def store_contiguous(a: wp.array(dtype=_vec3), i: int, value: _vec3):
        """``a[i] = value`` of a contiguous array (see ``load_contiguous``)."""

    @wp.func_native(f"return ((const {_ctype}*)a.data)[i];")
    def scalar_contiguous(a: wp.array(dtype=_scalar), i: int) -> _scalar:
        """``a[i]`` of a contiguous scalar array from its data pointer (see ``load_contiguous``)."""

    @wp.func_native(f"return ((const {_ctype}*)a.data)[j * a.shape[1] + k];")
    def entry_contiguous(a: wp.array2d(dtype=_scalar), j: int, k: int) -> _scalar:
        """``a[j, k]`` of a contiguous 2-d table from its data pointer."""


del _scalar, _ctype, _vec3


def _stage_values_through(load, store, entry, int_at, name):
    """The stage update, reading and writing per-particle arrays through ``load`` / ``store`` and the
    per-world tables through ``entry`` / ``int_at``; registered as the Warp function ``name``.

    Written once and instantiated twice below (``stage_values``, ``stage_values_direct``): the two
    differ only in how an element is addressed, never in arithmetic.
    """

    @wp.func(name=name)
    def stage_values(
        i: int,
        stage: int,
        h: Float,
        f: vec3,
        inv_mass: Float,
        w: int,
        gravity: vec3,
        world_stage_count: wp.array(dtype=wp.int32),
        world_symplectic: wp.array(dtype=wp.int32),
        world_stage_c: wp.array2d(dtype=Float),
        world_stage_b: wp.array2d(dtype=Float),
        q_n: wp.array(dtype=vec3),
        qd_n: wp.array(dtype=vec3),
        qd_s: wp.array(dtype=vec3),
        acc_q_out: wp.array(dtype=vec3),
        acc_qd_out: wp.array(dtype=vec3),
    ):
        """Stage ``stage`` of particle i (world w) given its force f at the stage state.

        Returns (kind, x, v): kind 0 when the world has fewer stages (nothing to write), 1 when
        (x, v) is the step's result y_{n+1}, 2 when (x, v) is the next stage state y_{s+1} (the
        accumulators are written here). The caller writes (x, v): ``integrate_stage`` below, and the
        fused lattice stage (kernels/lattice.py), which applies contact to them first and stores
        each particle once.
        """
        count = int_at(world_stage_count, w)
        if stage >= count:
            return 0, type(f)(type(h)(0.0)), type(f)(type(h)(0.0))
        a = acceleration(f, inv_mass, gravity)
        if int_at(world_symplectic, w) != 0:
            # Semi-implicit Euler: velocity first, then position with the new velocity.
            v_new = load(qd_n, i) + h * a
            return 1, load(q_n, i) + h * v_new, v_new
        v = load(qd_s, i)
        if count == 1:
            # Explicit Euler, the one-stage tableau (b = 1): the sums below without reading it
            # (b * v is v exactly, so the same bits).
            return 1, load(q_n, i) + h * v, load(qd_n, i) + h * a
        b = entry(world_stage_b, w, stage)
        acc_q = b * v
        acc_qd = b * a
        if stage == 1:
            # Stage 0's position term is b_0 v_n (its stage state is y_n): recomputed from the
            # v_n this stage reads anyway, not stored and loaded back (the same product, the
            # same bits, 24 bytes a particle less).
            acc_q = acc_q + entry(world_stage_b, w, 0) * load(qd_n, i)
            acc_qd = acc_qd + load(acc_qd_out, i)
        elif stage > 1:
            acc_q = acc_q + load(acc_q_out, i)
            acc_qd = acc_qd + load(acc_qd_out, i)
        if stage == count - 1:
            return 1, load(q_n, i) + h * acc_q, load(qd_n, i) + h * acc_qd
        if stage > 0:
            store(acc_q_out, i, acc_q)
        store(acc_qd_out, i, acc_qd)
        c = entry(world_stage_c, w, stage + 1)
        return 2, load(q_n, i) + (h * c) * v, load(qd_n, i) + (h * c) * a

    return stage_values


stage_values = _stage_values_through(load_indexed, store_indexed, entry_indexed, int_indexed, "stage_values")
"""The stage update through Warp's indexing (any arrays)."""
stage_values_direct = _stage_values_through(
    load_contiguous, store_contiguous, entry_contiguous, int_contiguous, "stage_values_direct"
)
"""The stage update through data pointers (contiguous arrays only): ``stage_values``'s arithmetic."""


@both_precisions
@wp.kernel
def integrate_stage(
    stage: int,
    h: Float,
    # Model:
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    gravity: vec3,
    world_stage_count: wp.array(dtype=wp.int32),
    world_symplectic: wp.array(dtype=wp.int32),
    world_stage_c: wp.array2d(dtype=Float),
    world_stage_b: wp.array2d(dtype=Float),
    # State in (y_n), stage state (y_s) and its forces:
    q_n: wp.array(dtype=vec3),
    qd_n: wp.array(dtype=vec3),
    q_s: wp.array(dtype=vec3),
    qd_s: wp.array(dtype=vec3),
    f_s: wp.array(dtype=vec3),
    # Out: accumulators, next stage state, and the step's result
    acc_q_out: wp.array(dtype=vec3),
    acc_qd_out: wp.array(dtype=vec3),
    q_next_out: wp.array(dtype=vec3),
    qd_next_out: wp.array(dtype=vec3),
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    kind, x, v = stage_values(
        i,
        stage,
        h,
        f_s[i],
        particle_inv_mass[i],
        particle_world[i],
        gravity,
        world_stage_count,
        world_symplectic,
        world_stage_c,
        world_stage_b,
        q_n,
        qd_n,
        qd_s,
        acc_q_out,
        acc_qd_out,
    )
    if kind == 1:
        q_out[i] = x
        qd_out[i] = v
    elif kind == 2:
        q_next_out[i] = x
        qd_next_out[i] = v

"""Integrator stages: explicit Runge-Kutta stages driven by a per-world tableau, and symplectic Euler.

Every explicit method here is written as stages of the first-order system y = (x, v), y' = (v, a):
stage s evaluates k_s = (v_s, a_s) at y_s, adds b_s k_s to an accumulator and forms the next stage
state y_{s+1} = y_n + h c_{s+1} k_s; the last stage writes y_{n+1} = y_n + h sum_s b_s k_s. The
tableau lives in arrays indexed by world, so one launch advances copies that use different methods
(the side-by-side comparison) and a single run is the one-world case.
"""

import functools

import warp as wp

wp.set_module_options({"enable_backward": False})


@functools.cache  # one set of Warp objects per precision, shared by every module that builds on it
def build(scalar):
    vec3 = wp.types.vector(3, scalar)
    ctype = "float" if scalar == wp.float32 else "double"

    @wp.func
    def acceleration(f: vec3, inv_mass: scalar, gravity: vec3):
        """a = f/m + g; a particle of infinite mass (inv_mass 0) does not move."""
        if inv_mass == scalar(0.0):
            return vec3(scalar(0.0))
        return f * inv_mass + gravity

    @wp.func
    def load_indexed(a: wp.array(dtype=vec3), i: int):
        return a[i]

    @wp.func
    def store_indexed(a: wp.array(dtype=vec3), i: int, value: vec3):
        a[i] = value

    @wp.func_native(
        f"const {ctype}* t = (const {ctype}*)a.data + 3 * i;\nreturn wp::vec_t<3, {ctype}>(t[0], t[1], t[2]);"
    )
    def load_contiguous(a: wp.array(dtype=vec3), i: int) -> vec3:
        """``a[i]`` of a contiguous array, addressed as data + 3 i scalars.

        Warp's ``a[i]`` wraps a negative index and multiplies by the array's run-time 64-bit stride
        (about 8 instructions an access on an H200); here the element size is a constant, so a
        neighbour's address is the particle's plus an offset the compiler folds into the load (the
        bare gather measured 1.24x faster on an H200), and the fused
        lattice stage's own loads and stores cost one address computation. Only for arrays the
        caller knows to be contiguous (``LatticeData.check_contiguous``).
        """

    @wp.func_native(f"{ctype}* t = ({ctype}*)a.data + 3 * i;\nt[0] = value[0]; t[1] = value[1]; t[2] = value[2];")
    def store_contiguous(a: wp.array(dtype=vec3), i: int, value: vec3):
        """``a[i] = value`` of a contiguous array (see ``load_contiguous``)."""

    @wp.func
    def int_indexed(a: wp.array(dtype=wp.int32), i: int):
        return a[i]

    @wp.func
    def scalar_indexed(a: wp.array(dtype=scalar), i: int):
        return a[i]

    @wp.func
    def entry_indexed(a: wp.array2d(dtype=scalar), j: int, k: int):
        return a[j, k]

    @wp.func_native("return ((const int*)a.data)[i];")
    def int_contiguous(a: wp.array(dtype=wp.int32), i: int) -> int:
        """``a[i]`` of a contiguous int32 array from its data pointer (see ``load_contiguous``)."""

    @wp.func_native(f"return ((const {ctype}*)a.data)[i];")
    def scalar_contiguous(a: wp.array(dtype=scalar), i: int) -> scalar:
        """``a[i]`` of a contiguous scalar array from its data pointer (see ``load_contiguous``)."""

    @wp.func_native(f"return ((const {ctype}*)a.data)[j * a.shape[1] + k];")
    def entry_contiguous(a: wp.array2d(dtype=scalar), j: int, k: int) -> scalar:
        """``a[j, k]`` of a contiguous 2-d table from its data pointer."""

    def make_stage_values(load, store, entry=entry_indexed, int_at=int_indexed):
        """``stage_values`` reading and writing per-particle arrays through ``load`` / ``store``
        (``load_indexed`` / ``store_indexed``: any array; the ``*_contiguous`` pair: contiguous ones)
        and the per-world tables through ``entry`` / ``int_at``."""

        @wp.func
        def stage_values(
            i: int,
            stage: int,
            h: scalar,
            f: vec3,
            inv_mass: scalar,
            w: int,
            gravity: vec3,
            world_stage_count: wp.array(dtype=wp.int32),
            world_symplectic: wp.array(dtype=wp.int32),
            world_stage_c: wp.array2d(dtype=scalar),
            world_stage_b: wp.array2d(dtype=scalar),
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
                return 0, vec3(scalar(0.0)), vec3(scalar(0.0))
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

    stage_values = make_stage_values(load_indexed, store_indexed)
    stage_values_direct = make_stage_values(load_contiguous, store_contiguous, entry_contiguous, int_contiguous)

    @wp.kernel(module="unique")
    def integrate_stage(
        stage: int,
        h: scalar,
        # Model:
        particle_inv_mass: wp.array(dtype=scalar),
        particle_world: wp.array(dtype=wp.int32),
        gravity: vec3,
        world_stage_count: wp.array(dtype=wp.int32),
        world_symplectic: wp.array(dtype=wp.int32),
        world_stage_c: wp.array2d(dtype=scalar),
        world_stage_b: wp.array2d(dtype=scalar),
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

    return {
        "acceleration": acceleration,
        "stage_values": stage_values,
        "stage_values_direct": stage_values_direct,
        "int_contiguous": int_contiguous,
        "entry_contiguous": entry_contiguous,
        "scalar_contiguous": scalar_contiguous,
        "int_indexed": int_indexed,
        "load_indexed": load_indexed,
        "scalar_indexed": scalar_indexed,
        "load_contiguous": load_contiguous,
        "store_contiguous": store_contiguous,
        "integrate_stage": integrate_stage,
    }

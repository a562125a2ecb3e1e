"""kernels/integration.py alone: its module-level funcs and the stage kernel, float32 and float64."""

import numpy as np
import pytest
import warp as wp
from softsim_warp.kernels import integration
from softsim_warp.kernels.precision import Float, both_precisions, vec3

TABLEAUX = {  # (c, b), as core/integrators.TABLEAUX
    "euler": ((0.0,), (1.0,)),
    "midpoint": ((0.0, 0.5), (0.0, 1.0)),
    "rk4": ((0.0, 0.5, 0.5, 1.0), (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)),
}
PRECISIONS = [(wp.float32, np.float32), (wp.float64, np.float64)]


@both_precisions
@wp.kernel
def acceleration_of(f: wp.array(dtype=vec3), inv_mass: wp.array(dtype=Float), g: vec3, a_out: wp.array(dtype=vec3)):
    i = wp.tid()
    a_out[i] = integration.acceleration(f[i], inv_mass[i], g)


@pytest.mark.parametrize("scalar,np_dtype", PRECISIONS)
def test_acceleration_is_f_over_m_plus_g_and_zero_for_pinned(device, scalar, np_dtype):
    vec = wp.types.vector(3, scalar)
    f = np.array([[1.0, -2.0, 3.0], [4.0, 5.0, 6.0]], dtype=np_dtype)
    inv_mass = np.array([0.5, 0.0], dtype=np_dtype)
    g = np.array([0.0, -9.81, 0.0], dtype=np_dtype)
    out = wp.zeros(2, dtype=vec, device=device)
    wp.launch(
        acceleration_of,
        2,
        inputs=[wp.array(f, dtype=vec, device=device), wp.array(inv_mass, dtype=scalar, device=device), vec(*g)],
        outputs=[out],
        device=device,
    )
    a = out.numpy()
    assert a.dtype == np_dtype
    np.testing.assert_array_equal(a[0], f[0] * inv_mass[0] + g)  # one multiply and one add per component
    np.testing.assert_array_equal(a[1], np.zeros(3, dtype=np_dtype))


def run_steps(device, scalar, np_dtype, method, direct, q0, v0, f, inv_mass, g, h, steps):
    """``steps`` steps of ``method`` under the constant force f, through ``integrate_stage``
    (``direct`` False) or a kernel around ``stage_values_direct`` (True)."""
    vec = wp.types.vector(3, scalar)
    c, b = TABLEAUX.get(method, ((0.0,), (1.0,)))
    n = len(q0)
    arr = lambda x: wp.array(np.asarray(x, dtype=np_dtype), dtype=vec, device=device)
    q_n, qd_n = arr(q0), arr(v0)
    q_s, qd_s = arr(q0), arr(v0)
    f_s = arr(f)
    acc_q, acc_qd = (wp.zeros(n, dtype=vec, device=device) for _ in range(2))
    q_next, qd_next = (wp.zeros(n, dtype=vec, device=device) for _ in range(2))
    q_out, qd_out = (wp.zeros(n, dtype=vec, device=device) for _ in range(2))
    tables = [
        wp.array(np.asarray(inv_mass, dtype=np_dtype), dtype=scalar, device=device),
        wp.zeros(n, dtype=wp.int32, device=device),
        vec(*g),
        wp.array([len(c)], dtype=wp.int32, device=device),
        wp.array([1 if method == "symplectic" else 0], dtype=wp.int32, device=device),
        wp.array2d(np.asarray([c], dtype=np_dtype), dtype=scalar, device=device),
        wp.array2d(np.asarray([b], dtype=np_dtype), dtype=scalar, device=device),
    ]
    kernel = integrate_stage_direct if direct else integration.integrate_stage
    for _ in range(steps):
        for stage in range(len(c)):
            state = (q_n, qd_n, q_s if stage == 0 else q_next, qd_s if stage == 0 else qd_next)
            wp.launch(
                kernel,
                n,
                inputs=[stage, scalar(h), *tables, *state, f_s],
                outputs=[acc_q, acc_qd, q_next, qd_next, q_out, qd_out],
                device=device,
            )
        wp.copy(q_n, q_out)
        wp.copy(qd_n, qd_out)
        wp.copy(q_s, q_out)
        wp.copy(qd_s, qd_out)
    return q_out.numpy(), qd_out.numpy()


@both_precisions
@wp.kernel
def integrate_stage_direct(
    stage: int,
    h: Float,
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    gravity: vec3,
    world_stage_count: wp.array(dtype=wp.int32),
    world_symplectic: wp.array(dtype=wp.int32),
    world_stage_c: wp.array2d(dtype=Float),
    world_stage_b: wp.array2d(dtype=Float),
    q_n: wp.array(dtype=vec3),
    qd_n: wp.array(dtype=vec3),
    q_s: wp.array(dtype=vec3),
    qd_s: wp.array(dtype=vec3),
    f_s: wp.array(dtype=vec3),
    acc_q_out: wp.array(dtype=vec3),
    acc_qd_out: wp.array(dtype=vec3),
    q_next_out: wp.array(dtype=vec3),
    qd_next_out: wp.array(dtype=vec3),
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    # integrate_stage with the data-pointer accessors, as the fused lattice stage reads them.
    i = wp.tid()
    kind, x, v = integration.stage_values_direct(
        i,
        stage,
        h,
        integration.load_contiguous(f_s, i),
        integration.scalar_contiguous(particle_inv_mass, i),
        integration.int_contiguous(particle_world, i),
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
        integration.store_contiguous(q_out, i, x)
        integration.store_contiguous(qd_out, i, v)
    elif kind == 2:
        integration.store_contiguous(q_next_out, i, x)
        integration.store_contiguous(qd_next_out, i, v)


@pytest.mark.parametrize("scalar,np_dtype", PRECISIONS)
@pytest.mark.parametrize("method", ["euler", "symplectic", "midpoint", "rk4"])
def test_constant_force_steps_match_closed_form_and_both_accessors_agree_bitwise(device, scalar, np_dtype, method):
    """Under a constant acceleration a every method here is exact up to rounding: v_n = v0 + a t
    (all of them), x_n = x0 + v0 t + a t^2 / 2 for midpoint and RK4 (second order suffices for a
    quadratic), x0 + v0 t + a t (t - h) / 2 for explicit Euler and x0 + v0 t + a t (t + h) / 2 for
    symplectic Euler. The indexed and data-pointer stage updates give the same bits on the CPU; on
    CUDA nvcc may fuse multiply-adds differently in the two kernels, so they agree to a few ulps."""
    rng = np.random.default_rng(7)
    n, h, steps = 5, 0.01, 6
    q0, v0, f = (rng.uniform(-1, 1, (n, 3)) for _ in range(3))
    inv_mass = np.array([2.0, 0.5, 1.0, 0.0, 4.0])
    g = np.array([0.0, -9.81, 0.0])
    args = (q0, v0, f, inv_mass, g, h, steps)
    q, v = run_steps(device, scalar, np_dtype, method, False, *args)
    q_direct, v_direct = run_steps(device, scalar, np_dtype, method, True, *args)
    if wp.get_device(device).is_cpu:
        np.testing.assert_array_equal(q, q_direct)
        np.testing.assert_array_equal(v, v_direct)
    else:
        np.testing.assert_array_max_ulp(q, q_direct, maxulp=4)
        np.testing.assert_array_max_ulp(v, v_direct, maxulp=4)
    a = np.where(inv_mass[:, None] == 0.0, 0.0, f * inv_mass[:, None] + g)
    t = h * steps
    shift = {"euler": -h, "symplectic": h}.get(method, 0.0)
    q_exact = q0 + v0 * t + 0.5 * a * t * (t + shift)
    v_exact = v0 + a * t
    # Rounding only: a few operations a stage, steps * stages of them, each within eps of |x| ~ 1.
    tol = 64 * np.finfo(np_dtype).eps * steps * len(TABLEAUX.get(method, ((0,),))[0])
    np.testing.assert_allclose(v, v_exact, rtol=0, atol=tol * 10)
    np.testing.assert_allclose(q, q_exact, rtol=0, atol=tol * 10)
    np.testing.assert_array_equal(v[3], v0[3].astype(np_dtype))  # a pinned particle keeps its velocity

"""The pin functions of kernels/pins.py alone, in both precisions, through one-thread kernels.

``rotate`` against a rotation matrix built from the axis-angle in NumPy (float64), and
``pin_position`` (hence ``rigid_pose`` and ``key_offset``) against the host path of
``core.pins.path_position``, for linear and Catmull-Rom keys, before, between and after them.
"""

import numpy as np
import pytest
import warp as wp

from softsim_warp.core.pins import make_motion, path_position
from softsim_warp.kernels import pins
from softsim_warp.kernels.precision import Float, both_precisions, vec3

PRECISIONS = {"float32": (wp.float32, np.float32, 2e-6), "float64": (wp.float64, np.float64, 1e-13)}


@both_precisions
@wp.kernel
def rotate_points(axis_angle: wp.array(dtype=vec3), r: wp.array(dtype=vec3), out: wp.array(dtype=vec3)):
    i = wp.tid()
    out[i] = pins.rotate(axis_angle[i], r[i])


@both_precisions
@wp.kernel
def pin_positions(
    t: wp.array(dtype=Float),
    x0: vec3,
    velocity: vec3,
    spin: vec3,
    center: vec3,
    count: int,
    smooth: int,
    key_time: wp.array(dtype=Float),
    key_value: wp.array(dtype=vec3),
    out: wp.array(dtype=vec3),
    centre_out: wp.array(dtype=vec3),
    turn_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    out[i] = pins.pin_position(t[i], x0, velocity, spin, center, 0, count, smooth, key_time, key_value)
    centre, turn = pins.rigid_pose(t[i], velocity, spin, center, 0, count, smooth, key_time, key_value)
    centre_out[i] = centre
    turn_out[i] = turn


def rotation_matrix(axis_angle):
    """Rodrigues' formula as a matrix: R = I + sin(a) K + (1 - cos(a)) K^2 for the unit axis's cross matrix K."""
    angle = np.linalg.norm(axis_angle)
    if angle == 0.0:
        return np.eye(3)
    k = axis_angle / angle
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * cross @ cross


@pytest.mark.parametrize("precision", PRECISIONS)
def test_rotate_matches_a_rotation_matrix(device, precision):
    scalar, np_scalar, tol = PRECISIONS[precision]
    v3 = wp.types.vector(3, scalar)
    rng = np.random.default_rng(4)
    axis_angle = rng.normal(size=(64, 3)) * 2.0
    axis_angle[0] = 0.0  # no turn at all: r comes back as it is
    r = rng.normal(size=(64, 3))
    out = wp.zeros(64, dtype=v3, device=device)
    wp.launch(rotate_points, 64, inputs=[wp.array(axis_angle.astype(np_scalar), dtype=v3, device=device),
                                         wp.array(r.astype(np_scalar), dtype=v3, device=device), out], device=device)
    got = out.numpy()
    expected = np.stack([rotation_matrix(a) @ x for a, x in zip(axis_angle.astype(np_scalar).astype(np.float64),
                                                                   r.astype(np_scalar).astype(np.float64))])
    assert got.dtype == np_scalar
    np.testing.assert_allclose(got, expected, rtol=0, atol=tol * 10)
    assert np.array_equal(got[0], r[0].astype(np_scalar))
    # A rotation keeps lengths.
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), np.linalg.norm(expected, axis=1), rtol=tol * 10)


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("interpolation", ["linear", "smooth"])
def test_pin_position_follows_the_host_path(device, precision, interpolation):
    scalar, np_scalar, tol = PRECISIONS[precision]
    v3 = wp.types.vector(3, scalar)
    motion = make_motion(velocity=(0.3, -0.1, 0.2), spin=(0.0, 1.5, 0.5), center=(0.5, 1.0, -0.25),
                         key_times=[0.1, 0.4, 0.5, 0.9], key_offsets=[[0, 0, 0], [0.2, 0.1, 0], [0.3, 0.0, -0.1],
                                                                      [0.0, 0.4, 0.2]],
                         interpolation=interpolation)
    x0 = np.array([1.0, 0.5, 0.75])
    times = np.array([0.0, 0.1, 0.25, 0.4, 0.45, 0.6, 0.8, 0.9, 1.3])
    arrays = [wp.zeros(times.size, dtype=v3, device=device) for _ in range(3)]
    wp.launch(pin_positions, times.size,
              inputs=[wp.array(times.astype(np_scalar), dtype=scalar, device=device), v3(*x0), v3(*motion["velocity"]),
                      v3(*motion["spin"]), v3(*motion["center"]), len(motion["key_times"]),
                      int(interpolation == "smooth"),
                      wp.array(np.array(motion["key_times"], dtype=np_scalar), dtype=scalar, device=device),
                      wp.array(np.array(motion["key_offsets"], dtype=np_scalar), dtype=v3, device=device), *arrays],
              device=device)
    got, centre, turn = (a.numpy() for a in arrays)
    expected = np.stack([path_position(motion, x0, t) for t in times])
    np.testing.assert_allclose(got, expected, rtol=0, atol=tol * 10)
    # The pose: the centre's own path (X = c) and the turn w t.
    np.testing.assert_allclose(centre, np.stack([path_position(motion, motion["center"], t) for t in times]),
                               rtol=0, atol=tol * 10)
    np.testing.assert_allclose(turn, times[:, None] * motion["spin"], rtol=0, atol=tol * 10)

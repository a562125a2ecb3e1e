"""Driven pins: particles that follow a prescribed path (``softsim_warp.core.pins``).

A pinned particle has inverse mass 0, so no force accelerates it and every integrator moves it by
exactly ``h v`` in a step (``x_{n+1} = x_n + h v_n`` for every Runge-Kutta method, the symplectic
and the implicit one alike). At the start of each step ``drive_pins`` puts it on its path at the
step's start time and gives it the velocity that lands it on the path at the step's end,
``v = (P(t + h) - P(t)) / h``, so it follows ``P`` exactly at every step, whatever the method. The
path of pin ``p`` for a particle that starts at ``X`` is

    P(t) = c + v t + d(t) + R(w t) (X - c)

with the pin's velocity ``v``, its spin ``w`` (rad/s about the axis ``w / |w|``) about the centre
``c`` (which moves with ``v``), and ``d(t)`` the pin's keyframed offset, interpolated linearly or by
a Catmull-Rom spline (``smooth``), held before the first key and after the last.
"""

import warp as wp

from .precision import Float, both_precisions, vec3

wp.set_module_options({"enable_backward": False})


@wp.func
def rotate(axis_angle: vec3, r: vec3):
    """Rodrigues: ``r`` turned by ``|axis_angle|`` radians about ``axis_angle``."""
    angle = wp.length(axis_angle)
    if angle == type(angle)(0.0):
        return r
    k = axis_angle / angle
    c = wp.cos(angle)
    s = wp.sin(angle)
    return r * c + wp.cross(k, r) * s + k * (wp.dot(k, r) * (type(angle)(1.0) - c))


@wp.func
def key_interval(t: Float, first: int, count: int, times: wp.array(dtype=Float)):
    """Where ``t`` falls among the increasing ``times[first], ..., times[first + count - 1]``
    (count > 0): (k, u, held). At or outside the ends ``held`` is 1 and ``k`` the end key that is
    held; otherwise ``t`` lies in ``[times[k], times[k + 1]]`` at the fraction ``u`` of it. Shared by
    the keyframed offsets here and the animated meshes' vertex samples (kernels/mesh.py)."""
    last = first + count - 1
    if t <= times[first]:
        return first, type(t)(0.0), 1
    if t >= times[last]:
        return last, type(t)(0.0), 1
    k = first
    while times[k + 1] < t:
        k += 1
    return k, (t - times[k]) / (times[k + 1] - times[k]), 0


@wp.func
def key_offset(t: Float, first: int, count: int, smooth: int, key_time: wp.array(dtype=Float),
               key_value: wp.array(dtype=vec3)):
    """The keyframed offset at ``t``: held outside the keys, linear or Catmull-Rom between them."""
    if count == 0:
        return wp.vector(type(t)(0.0), length=3)
    k, u, held = key_interval(t, first, count, key_time)
    if held != 0:
        return key_value[k]
    last = first + count - 1
    t0 = key_time[k]
    t1 = key_time[k + 1]
    p0 = key_value[k]
    p1 = key_value[k + 1]
    if smooth == 0:
        return p0 + (p1 - p0) * u
    # Cubic Hermite with Catmull-Rom tangents for unevenly spaced keys (one-sided at the ends).
    m0 = (p1 - p0) / (t1 - t0)
    if k > first:
        m0 = (p1 - key_value[k - 1]) / (t1 - key_time[k - 1])
    m1 = (p1 - p0) / (t1 - t0)
    if k + 1 < last:
        m1 = (key_value[k + 2] - p0) / (key_time[k + 2] - t0)
    u2 = u * u
    u3 = u2 * u
    h00 = type(t)(2.0) * u3 - type(t)(3.0) * u2 + type(t)(1.0)
    h10 = u3 - type(t)(2.0) * u2 + u
    h01 = type(t)(-2.0) * u3 + type(t)(3.0) * u2
    h11 = u3 - u2
    dt = t1 - t0
    return p0 * h00 + m0 * (h10 * dt) + p1 * h01 + m1 * (h11 * dt)


@wp.func
def rigid_pose(t: Float, velocity: vec3, spin: vec3, center: vec3, first: int, count: int, smooth: int,
               key_time: wp.array(dtype=Float), key_value: wp.array(dtype=vec3)):
    """The pose of a motion at ``t``: where its centre has gone, ``c + v t + d(t)``, and its turn
    (axis-angle) ``w t``; a point that starts at ``X`` is then at ``centre + rotate(turn, X - c)``.
    Shared by the pins and the moving terrain (kernels/contact.py ``move_terrain``)."""
    return center + velocity * t + key_offset(t, first, count, smooth, key_time, key_value), spin * t


@wp.func
def pin_position(t: Float, x0: vec3, velocity: vec3, spin: vec3, center: vec3, first: int, count: int,
                 smooth: int, key_time: wp.array(dtype=Float), key_value: wp.array(dtype=vec3)):
    moved, turn = rigid_pose(t, velocity, spin, center, first, count, smooth, key_time, key_value)
    return moved + rotate(turn, x0 - center)


@both_precisions
@wp.kernel
def drive_pins(
    clock: wp.array(dtype=wp.int32),
    h: Float,
    # Driven particles:
    particle: wp.array(dtype=wp.int32),
    pin: wp.array(dtype=wp.int32),
    start: wp.array(dtype=vec3),
    # Pins:
    pin_velocity: wp.array(dtype=vec3),
    pin_spin: wp.array(dtype=vec3),
    pin_center: wp.array(dtype=vec3),
    pin_key_first: wp.array(dtype=wp.int32),
    pin_key_count: wp.array(dtype=wp.int32),
    pin_smooth: wp.array(dtype=wp.int32),
    key_time: wp.array(dtype=Float),
    key_value: wp.array(dtype=vec3),
    # In/out: the state the step starts from
    q: wp.array(dtype=vec3),
    qd: wp.array(dtype=vec3),
):
    k = wp.tid()
    p = pin[k]
    t0 = type(h)(clock[0]) * h
    first = pin_key_first[p]
    count = pin_key_count[p]
    smooth = pin_smooth[p]
    x0 = pin_position(t0, start[k], pin_velocity[p], pin_spin[p], pin_center[p], first, count, smooth,
                      key_time, key_value)
    x1 = pin_position(t0 + h, start[k], pin_velocity[p], pin_spin[p], pin_center[p], first, count, smooth,
                      key_time, key_value)
    i = particle[k]
    q[i] = x0
    qd[i] = (x1 - x0) / h


@wp.kernel
def advance_pin_clock(clock: wp.array(dtype=wp.int32)):
    clock[0] = clock[0] + 1

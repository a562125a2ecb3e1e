"""Terrain contact: collision with restitution, resting contact and Coulomb friction.

Contact runs once per step, after the integrator has advanced the smooth forces (springs and
gravity) from y_n to y*. Runge-Kutta stages assume a smooth right-hand side; applying impulses to
trial states (inside every force evaluation) would change stage states that the method later
combines, so midpoint and RK4 would lose their meaning and could inject energy. Splitting contact
off keeps every integrator's smooth part exact in its order and treats all of them alike at
impacts, where every method is first order anyway.

The one exception is resting contact in the intermediate stages of midpoint and RK4
(``integrators.filter_stage_contacts``): a stage state lets a particle resting on a surface move
into it, and the springs' dampers would answer that fictitious velocity and take part of the normal
force that friction depends on. So the stage velocities of particles that the response would hold
get the contact branch (normal approach cancelled, friction), never an impact or a position change.

The response is written once, at the top of this module: ``resolve_contact`` (restitution, resting
contact, ``coulomb_friction``) and, for a moving surface, ``resolve_moving`` (the same in the frame
of the surface's velocity at the particle, ``surface_velocity``). Every primitive only supplies the
signed distance and the outward normal at the particle (``plane_distance``, ``bowl_distance``,
``sphere_distance``; ``mesh_distance`` in kernels/mesh.py), and every kernel that resolves terrain
contact calls the response: the ``collide_*`` kernels here and in kernels/mesh.py, and the fused
lattice stage through ``contact_planes_direct``. Impact or contact is decided by a restitution
threshold derived from the particle's own pressing impulse over the step (see its comments and
docs/SCENES.md, "Impact or contact").

Where a particle touches: ``contact_epsilon`` is the layer within which a surface is looked at
(and where the implicit solve finds the surface a particle touches), but the response acts only
once the step carries the particle to the surface, within :data:`TOUCH_FRACTION` of the layer (the
rounding of a projection onto a tilted or curved surface). A particle that crosses is put back on
the surface, so a jelly comes to rest on it, not on top of the layer (docs/SCENES.md, "Where a
particle touches").
"""

import warp as wp

from . import integration
from .pins import rigid_pose, rotate
from .precision import Float, both_precisions, vec3

wp.set_module_options({"enable_backward": False})

# A particle touches a surface once its step brings it within this fraction of contact_epsilon of
# it (or through it). Contact across the whole layer would hold a slowly settling particle wherever
# it entered the layer, so a resting jelly would stand up to contact_epsilon above the ground. The
# fraction only has to cover the rounding of a particle put back on the surface (1e-7 of a unit in
# float32), which must still count as touching on the next step.
TOUCH_FRACTION = 1.0e-3
# The ``stage`` argument of the response that lets a particle touch anywhere within contact_epsilon:
# the implicit contact solve constrains every particle at the surface or about to reach it (a stiff
# lattice needs them all in the solve: with only those that reached the surface, the solve drives
# the others into the ground, and putting them back after it adds energy at an impact).
LAYER_TOUCH = -1
# The signed distance that stands for "no surface here": over a plane's hole, above a bowl's cut.
NO_SURFACE = 1.0e30


# -- The response: restitution and friction, shared by every surface ------------------------------


@wp.func
def coulomb_friction(vt: vec3, budget: Float):
    """Coulomb friction on a tangential velocity: at most ``budget`` of its speed removed, never
    reversing it (a speed within the budget sticks)."""
    speed = wp.length(vt)
    v_new = type(vt)(type(budget)(0.0))
    if speed > budget:
        v_new = vt * ((speed - budget) / speed)
    return v_new


@wp.func
def resolve_contact(
    x: vec3,
    v: vec3,
    vn_prev: Float,
    phi: Float,
    normal: vec3,
    restitution: Float,
    friction: Float,
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    beta_h: Float,
    stage: int,
):
    """Contact response of one particle against one surface; returns the new (x, v).

    phi is the signed distance after the step (positive outside) and normal the outward unit
    normal there; vn_prev is the normal velocity before the step, measured along the surface's
    normal at the step's start point. beta_h is h times the position gain the integrator gives a
    constant force over the step (dx = beta h dv; ``core/methods.Method.contact_beta``): 1 for
    symplectic and implicit Euler, 0 for explicit Euler, and 0 for midpoint and RK4 too, whose
    stage states already carry the contact force of resting particles (``filter_stage_contacts``).

    stage > 0 filters an intermediate Runge-Kutta stage state instead (x, v = y_n + h c_s k):
    only the contact branch acts, on the velocity (see ``filter_stage_contacts``).

    The particle touches when phi < TOUCH_FRACTION eps: the step has carried it to the surface
    (see the module docstring); a particle still above that moves on freely this step. stage < 0
    (:data:`LAYER_TOUCH`) lets it touch anywhere within eps: the implicit integrator's response
    on its free result, which picks the particles its contact solve constrains.
    """
    if phi >= touch_distance(eps, stage):
        return x, v
    vn = wp.dot(normal, v)
    if vn < type(phi)(0.0):
        # Impact or contact? The approach speed after the step, -vn, is what the particle
        # brought into the step, u0 = -vn_prev, plus what the step added, w: the forces of
        # the step pressing it in (gravity and springs, h |f.n| / m) and, on a concave surface,
        # the surface turning under a sliding particle (|v|^2 h / R). Only u0 is an impact
        # speed: w is the impulse of a force acting over the step, and reflecting it bounces
        # a particle that the force presses back within a step or two (a pressed particle
        # settles into reflecting e w / (1 + e) every step, and a resting jelly never comes to
        # rest). So, as Box2D, Bullet and Guendelman et al. 2003 do with a restitution
        # velocity threshold, an approach slower than rest_steps steps of the particle's own
        # pressing impulse (u0 < rest_steps w), or slower than eps_v, is a contact:
        # inelastic, with Coulomb friction. The threshold follows the force and the step
        # (it vanishes with h), so impacts well above it keep their restitution exactly.
        u0 = -vn_prev
        w = -vn - u0
        if stage > 0:
            if u0 < eps_v or u0 < rest_steps * w:
                v = coulomb_friction(v - vn * normal, friction * (-vn))
            return x, v
        if u0 < eps_v or u0 < rest_steps * w:
            # Cancel the normal velocity (the particle stays on the surface) and let Coulomb
            # friction remove at most mu times that normal impulse per unit mass, -vn, of
            # tangential speed, never reversing it. On a flat surface resting -vn = |N.f| h / m;
            # on a curved one it also holds the centripetal part m |v|^2 h / R of the normal force.
            v_new = coulomb_friction(v - vn * normal, friction * (-vn))
            # Contact and friction act as forces over the whole step: move the position by
            # what the integrator would have made of them, so a stuck particle does not creep.
            # Along the normal that is at most back onto the surface: the approach stops on
            # it, not where the step began (which would leave a particle that touched within
            # its step's approach, (f.n / m) h^2, above the surface for good).
            dx = beta_h * (v_new - v)
            lift = wp.dot(normal, dx)
            landed = wp.min(lift, wp.max(-phi, type(phi)(0.0)))
            x = x + dx - (lift - landed) * normal
            phi = phi + landed
            v = v_new
        else:
            # Impact: reflect the approaching normal velocity; Coulomb friction removes at
            # most mu times the normal impulse (1 + e)(-vn) of tangential speed.
            v_tangent = coulomb_friction(v - vn * normal, friction * (type(restitution)(1.0) + restitution) * (-vn))
            v = v_tangent - restitution * vn * normal
    # A particle that moves away after the step (vn >= 0; on a convex surface the tangent of
    # the last step points outward by |v| h / R) is separating: the surface pushes nothing, so
    # neither normal cancellation nor friction applies (cancelling it would glue particles to
    # a sphere well past the point where they fly off); it is only put back on the surface.
    if phi < type(phi)(0.0):
        x = x - phi * normal
    return x, v


@wp.func
def touch_distance(eps: Float, stage: int):
    """The signed distance below which a particle touches a surface: within :data:`TOUCH_FRACTION`
    of the contact layer, or anywhere in it for the implicit solve's pick (stage < 0,
    :data:`LAYER_TOUCH`). See ``resolve_contact``."""
    touch = eps * type(eps)(TOUCH_FRACTION)
    if stage < 0:
        touch = eps
    return touch


@wp.func
def surface_velocity(x: vec3, m: int, motion_center_now: wp.array(dtype=vec3),
                     motion_velocity_step: wp.array(dtype=vec3), motion_spin: wp.array(dtype=vec3)):
    """Velocity of moving primitive ``m``'s surface at ``x`` over the step (0 for m < 0, static):
    its centre's velocity plus its spin about that centre."""
    if m < 0:
        return type(x)()
    return motion_velocity_step[m] + wp.cross(motion_spin[m], x - motion_center_now[m])


@wp.func
def resolve_moving(
    x: vec3,
    v: vec3,
    v_prev: vec3,
    normal_prev: vec3,
    v_surface: vec3,
    phi: Float,
    normal: vec3,
    restitution: Float,
    friction: Float,
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    beta_h: Float,
    stage: int,
):
    """``resolve_contact`` in the frame of a surface moving at ``v_surface`` at the particle: the
    velocities before (along ``normal_prev``) and after the step are taken relative to it.
    A particle that does not touch is returned untouched (not v - v_surface + v_surface, which rounds)."""
    if phi >= touch_distance(eps, stage):
        return x, v
    x, v_rel = resolve_contact(x, v - v_surface, wp.dot(normal_prev, v_prev - v_surface), phi, normal, restitution,
                               friction, eps, eps_v, rest_steps, beta_h, stage)
    return x, v_rel + v_surface


# -- Surfaces: each gives the response its signed distance and outward normal at the particle -----


@wp.func
def plane_distance(x: vec3, point: vec3, normal: vec3, hole_center: vec3, hole_radius: Float):
    """Signed distance to a plane; a huge value over its hole, where the plane does not collide."""
    phi = wp.dot(x - point, normal)
    if hole_radius > type(hole_radius)(0.0):
        r = x - hole_center
        r = r - wp.dot(r, normal) * normal
        if wp.length_sq(r) < hole_radius * hole_radius:
            return type(hole_radius)(NO_SURFACE)
    return phi


def _contact_planes_through(int_at, vec_at, name):
    """``contact_planes`` reading the world's plane range and each plane's point and normal (what
    every particle reads) through ``int_at`` / ``vec_at``; registered as the Warp function ``name``.

    Written once and instantiated twice below: ``contact_planes`` through Warp's indexing,
    ``contact_planes_direct`` through the data pointers of contiguous arrays for the fused lattice
    stage (kernels/integration.py's ``*_contiguous``). The two differ only in how an element is
    addressed, never in arithmetic."""

    @wp.func(name=name)
    def contact_planes(
        x: vec3,
        v: vec3,
        v_prev: wp.array(dtype=vec3),
        i: int,
        w: int,
        plane_first: wp.array(dtype=wp.int32),
        plane_point: wp.array(dtype=vec3),
        plane_normal: wp.array(dtype=vec3),
        plane_hole_center: wp.array(dtype=vec3),
        plane_hole_radius: wp.array(dtype=Float),
        plane_restitution: wp.array(dtype=Float),
        plane_friction: wp.array(dtype=Float),
        eps: Float,
        eps_v: Float,
        rest_steps: Float,
        beta_h: Float,
        stage: int,
    ):
        """Particle i of world ``w`` against every plane of that world; returns the new (x, v).

        ``v_prev[i]`` is the particle's velocity before the step. Shared by ``collide_planes`` and
        the fused stages of the lattice path, where most particles are nowhere near a plane: the
        hole, the coefficients and the previous velocity are read only within ``eps`` of it.
        """
        # The planes of world w are plane_first[w] .. plane_first[w + 1] - 1 (sorted by world).
        for p in range(int_at(plane_first, w), int_at(plane_first, w + 1)):
            n = vec_at(plane_normal, p)
            point = vec_at(plane_point, p)
            if wp.dot(x - point, n) < eps:
                # The same distance again, now with the hole (which only ever removes contact).
                phi = plane_distance(x, point, n, plane_hole_center[p], plane_hole_radius[p])
                x, v = resolve_contact(
                    x,
                    v,
                    wp.dot(n, v_prev[i]),
                    phi,
                    n,
                    plane_restitution[p],
                    plane_friction[p],
                    eps,
                    eps_v,
                    rest_steps,
                    beta_h,
                    stage,
                )
        return x, v

    return contact_planes


contact_planes = _contact_planes_through(integration.int_indexed, integration.load_indexed, "contact_planes")
contact_planes_direct = _contact_planes_through(integration.int_contiguous, integration.load_contiguous,
                                                "contact_planes_direct")


# -- Bowls and spheres ----------------------------------------------------------------------
# Curved primitives give resolve_contact the distance and normal at the particle itself; a
# step's straight move leaves a curved surface by O(|v|^2 h^2 / R), which the position
# correction takes back, so a particle sliding along the surface follows the curve.


@wp.func
def bowl_distance(x: vec3, center: vec3, radius: Float, cut_height: Float):
    """Signed distance to a bowl (inside of a sphere where y < cut_height), positive inside.

    Returns (phi, inward normal); phi is a huge value at or above the cut, where the bowl does
    not exist.
    """
    d = center - x
    r = wp.length(d)
    n = type(x)(type(radius)(0.0), type(radius)(1.0), type(radius)(0.0))
    if r > type(radius)(0.0):
        n = d / r
    if x[1] >= cut_height:
        return type(radius)(NO_SURFACE), n
    return radius - r, n


@wp.func
def sphere_distance(x: vec3, center: vec3, radius: Float):
    """Signed distance to a solid sphere, positive outside; returns (phi, outward normal)."""
    d = x - center
    r = wp.length(d)
    # At the centre every direction is as good; push up, where the particle is most likely from.
    n = type(x)(type(radius)(0.0), type(radius)(1.0), type(radius)(0.0))
    if r > type(radius)(0.0):
        n = d / r
    return r - radius, n


@wp.func
def bowl_holds(x_prev: vec3, center: vec3, radius: Float, eps: Float):
    """Whether a bowl holds a particle that began the step at ``x_prev``, and the sphere's
    outward normal there: (holds, normal).

    The bowl holds what is inside it: a particle that began the step outside the sphere
    (beyond the contact layer and float rounding of a corrected position) is behind the shell
    and passes, instead of being pulled through the wall to the inside.
    """
    phi_out, n_out = sphere_distance(x_prev, center, radius)
    return phi_out <= eps + radius * type(radius)(1.0e-4), n_out


@wp.func
def moving_bowl_distance(x: vec3, center: vec3, radius: Float, cut_height: Float, m: int,
                         motion_turn_now: wp.array(dtype=vec3), motion_rest_point: wp.array(dtype=vec3)):
    """``bowl_distance`` of a bowl that may move (moving index ``m``, -1: static, ``center`` its
    centre now): a moving bowl's cut is a height in its own frame, so it turns with the bowl.
    Returns (phi, inward normal)."""
    cut = cut_height
    above = False
    if m >= 0:
        above = rotate(-motion_turn_now[m], x - center)[1] + motion_rest_point[m][1] >= cut_height
        cut = type(radius)(NO_SURFACE)
    phi, n = bowl_distance(x, center, radius, cut)
    if above:
        phi = type(radius)(NO_SURFACE)
    return phi, n


@wp.func
def contact_bowls(
    x: vec3,
    v: vec3,
    x_prev: vec3,
    v_prev: vec3,
    w: int,
    bowl_first: wp.array(dtype=wp.int32),
    bowl_center: wp.array(dtype=vec3),
    bowl_radius: wp.array(dtype=Float),
    bowl_cut_height: wp.array(dtype=Float),
    bowl_restitution: wp.array(dtype=Float),
    bowl_friction: wp.array(dtype=Float),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    beta_h: Float,
    stage: int,
):
    """One particle of world ``w`` against every bowl of that world; returns the new (x, v)."""
    # The bowls of world w are bowl_first[w] .. bowl_first[w + 1] - 1 (sorted by world).
    for b in range(bowl_first[w], bowl_first[w + 1]):
        c = bowl_center[b]
        radius = bowl_radius[b]
        holds, n_out = bowl_holds(x_prev, c, radius, eps)
        if holds:
            phi, n = bowl_distance(x, c, radius, bowl_cut_height[b])
            # The bowl's normal at the step's start is the sphere's, turned inward.
            x, v = resolve_contact(
                x,
                v,
                -wp.dot(n_out, v_prev),
                phi,
                n,
                bowl_restitution[b],
                bowl_friction[b],
                eps,
                eps_v,
                rest_steps,
                beta_h,
                stage,
            )
    return x, v


@wp.func
def contact_spheres(
    x: vec3,
    v: vec3,
    x_prev: vec3,
    v_prev: vec3,
    w: int,
    sphere_first: wp.array(dtype=wp.int32),
    sphere_center: wp.array(dtype=vec3),
    sphere_radius: wp.array(dtype=Float),
    sphere_restitution: wp.array(dtype=Float),
    sphere_friction: wp.array(dtype=Float),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    beta_h: Float,
    stage: int,
):
    """One particle of world ``w`` against every solid sphere of that world; returns the new (x, v)."""
    # The spheres of world w are sphere_first[w] .. sphere_first[w + 1] - 1 (sorted by world).
    for s in range(sphere_first[w], sphere_first[w + 1]):
        c = sphere_center[s]
        radius = sphere_radius[s]
        phi, n = sphere_distance(x, c, radius)
        phi_prev, n_prev = sphere_distance(x_prev, c, radius)
        x, v = resolve_contact(
            x,
            v,
            wp.dot(n_prev, v_prev),
            phi,
            n,
            sphere_restitution[s],
            sphere_friction[s],
            eps,
            eps_v,
            rest_steps,
            beta_h,
            stage,
        )
    return x, v


# -- Moving terrain ---------------------------------------------------------------------------
# A moving primitive follows a pin's motion (kernels/pins.py ``rigid_pose``): its geometry arrays
# (plane point, normal and hole; bowl and sphere centre) are overwritten at the start of every
# step with its pose at the step's end by ``move_terrain``, and the ``collide_moving_*``
# kernels below resolve contact in the primitive's frame: the surface's velocity at the
# particle is taken off before ``resolve_contact`` (restitution acts on the relative normal
# speed, friction on the relative tangential one) and added back after it. A scene whose
# terrain does not move never launches these: the static kernels above read no motion.


@both_precisions
@wp.kernel
def move_terrain(
    clock: wp.array(dtype=wp.int32),
    h: Float,
    # Per moving primitive: what it is, its geometry at rest and its motion (as a pin's).
    motion_kind: wp.array(dtype=wp.int32),
    motion_item: wp.array(dtype=wp.int32),
    motion_rest_point: wp.array(dtype=vec3),
    motion_rest_normal: wp.array(dtype=vec3),
    motion_rest_hole: wp.array(dtype=vec3),
    motion_velocity: wp.array(dtype=vec3),
    motion_spin: wp.array(dtype=vec3),
    motion_center: wp.array(dtype=vec3),
    motion_key_first: wp.array(dtype=wp.int32),
    motion_key_count: wp.array(dtype=wp.int32),
    motion_smooth: wp.array(dtype=wp.int32),
    key_time: wp.array(dtype=Float),
    key_value: wp.array(dtype=vec3),
    # Out, per moving primitive: its motion's centre and turn at the step's end, the centre's
    # velocity over the step, and its reference point at the step's start.
    motion_center_now: wp.array(dtype=vec3),
    motion_turn_now: wp.array(dtype=vec3),
    motion_velocity_step: wp.array(dtype=vec3),
    motion_point_prev: wp.array(dtype=vec3),
    # Out: the terrain's geometry at the step's end.
    plane_point: wp.array(dtype=vec3),
    plane_normal: wp.array(dtype=vec3),
    plane_hole_center: wp.array(dtype=vec3),
    bowl_center: wp.array(dtype=vec3),
    sphere_center: wp.array(dtype=vec3),
):
    # One thread for all moving primitives (a scene has a few) and the clock: one launch a step,
    # and no other thread reads the clock while it advances.
    t0 = type(h)(clock[0]) * h
    for m in range(motion_kind.shape[0]):
        first = motion_key_first[m]
        count = motion_key_count[m]
        smooth = motion_smooth[m]
        c = motion_center[m]
        center_start, turn_start = rigid_pose(t0, motion_velocity[m], motion_spin[m], c, first, count, smooth,
                                              key_time, key_value)
        center_end, turn_end = rigid_pose(t0 + h, motion_velocity[m], motion_spin[m], c, first, count, smooth,
                                          key_time, key_value)
        rest = motion_rest_point[m]
        point_end = center_end + rotate(turn_end, rest - c)
        motion_center_now[m] = center_end
        motion_turn_now[m] = turn_end
        motion_velocity_step[m] = (center_end - center_start) / h
        motion_point_prev[m] = center_start + rotate(turn_start, rest - c)
        k = motion_item[m]
        kind = motion_kind[m]
        if kind == 0:
            plane_point[k] = point_end
            plane_normal[k] = rotate(turn_end, motion_rest_normal[m])
            plane_hole_center[k] = center_end + rotate(turn_end, motion_rest_hole[m] - c)
        elif kind == 1:
            bowl_center[k] = point_end
        elif kind == 2:
            sphere_center[k] = point_end
        # A mesh (kind 3) stays where it was built: its contact reads the pose (kernels/mesh.py).
    clock[0] = clock[0] + 1


# -- Kernels: one per primitive kind, so a scene launches only the kinds it has -------------
# core/contact.py launches them all alike: (particle_inv_mass, particle_world, the kind's arrays
# (first per world, then its parameters)..., eps, eps_v, rest_steps, h, world_contact_beta, stage,
# q_prev, qd_prev) in, (q_out, qd_out) corrected in place; each thread touches only its own particle.


@both_precisions
@wp.kernel
def collide_planes(
    # Model:
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    plane_first: wp.array(dtype=wp.int32),
    plane_point: wp.array(dtype=vec3),
    plane_normal: wp.array(dtype=vec3),
    plane_hole_center: wp.array(dtype=vec3),
    plane_hole_radius: wp.array(dtype=Float),
    plane_restitution: wp.array(dtype=Float),
    plane_friction: wp.array(dtype=Float),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    h: Float,
    world_contact_beta: wp.array(dtype=Float),
    stage: int,
    # State before the step:
    q_prev: wp.array(dtype=vec3),
    qd_prev: wp.array(dtype=vec3),
    # State after the step, corrected in place:
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    if particle_inv_mass[i] != type(h)(0.0):
        w = particle_world[i]
        x, v = contact_planes(
            q_out[i],
            qd_out[i],
            qd_prev,
            i,
            w,
            plane_first,
            plane_point,
            plane_normal,
            plane_hole_center,
            plane_hole_radius,
            plane_restitution,
            plane_friction,
            eps,
            eps_v,
            rest_steps,
            h * world_contact_beta[w],
            stage,
        )
        q_out[i] = x
        qd_out[i] = v


@both_precisions
@wp.kernel
def collide_bowls(
    # Model:
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    bowl_first: wp.array(dtype=wp.int32),
    bowl_center: wp.array(dtype=vec3),
    bowl_radius: wp.array(dtype=Float),
    bowl_cut_height: wp.array(dtype=Float),
    bowl_restitution: wp.array(dtype=Float),
    bowl_friction: wp.array(dtype=Float),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    h: Float,
    world_contact_beta: wp.array(dtype=Float),
    stage: int,
    # State before the step:
    q_prev: wp.array(dtype=vec3),
    qd_prev: wp.array(dtype=vec3),
    # State after the step, corrected in place:
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    if particle_inv_mass[i] != type(h)(0.0):
        w = particle_world[i]
        x, v = contact_bowls(
            q_out[i],
            qd_out[i],
            q_prev[i],
            qd_prev[i],
            w,
            bowl_first,
            bowl_center,
            bowl_radius,
            bowl_cut_height,
            bowl_restitution,
            bowl_friction,
            eps,
            eps_v,
            rest_steps,
            h * world_contact_beta[w],
            stage,
        )
        q_out[i] = x
        qd_out[i] = v


@both_precisions
@wp.kernel
def collide_spheres(
    # Model:
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    sphere_first: wp.array(dtype=wp.int32),
    sphere_center: wp.array(dtype=vec3),
    sphere_radius: wp.array(dtype=Float),
    sphere_restitution: wp.array(dtype=Float),
    sphere_friction: wp.array(dtype=Float),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    h: Float,
    world_contact_beta: wp.array(dtype=Float),
    stage: int,
    # State before the step:
    q_prev: wp.array(dtype=vec3),
    qd_prev: wp.array(dtype=vec3),
    # State after the step, corrected in place:
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    if particle_inv_mass[i] != type(h)(0.0):
        w = particle_world[i]
        x, v = contact_spheres(
            q_out[i],
            qd_out[i],
            q_prev[i],
            qd_prev[i],
            w,
            sphere_first,
            sphere_center,
            sphere_radius,
            sphere_restitution,
            sphere_friction,
            eps,
            eps_v,
            rest_steps,
            h * world_contact_beta[w],
            stage,
        )
        q_out[i] = x
        qd_out[i] = v

# The moving variants take, after the kind's own arrays, each primitive's moving index (-1:
# static) and the arrays ``move_terrain`` writes, then the same arguments as the static ones.


@both_precisions
@wp.kernel
def collide_moving_planes(
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    plane_first: wp.array(dtype=wp.int32),
    plane_point: wp.array(dtype=vec3),
    plane_normal: wp.array(dtype=vec3),
    plane_hole_center: wp.array(dtype=vec3),
    plane_hole_radius: wp.array(dtype=Float),
    plane_restitution: wp.array(dtype=Float),
    plane_friction: wp.array(dtype=Float),
    plane_motion: wp.array(dtype=wp.int32),
    motion_center_now: wp.array(dtype=vec3),
    motion_turn_now: wp.array(dtype=vec3),
    motion_velocity_step: wp.array(dtype=vec3),
    motion_point_prev: wp.array(dtype=vec3),
    motion_spin: wp.array(dtype=vec3),
    motion_rest_point: wp.array(dtype=vec3),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    h: Float,
    world_contact_beta: wp.array(dtype=Float),
    stage: int,
    q_prev: wp.array(dtype=vec3),
    qd_prev: wp.array(dtype=vec3),
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    if particle_inv_mass[i] != type(h)(0.0):
        w = particle_world[i]
        x = q_out[i]
        v = qd_out[i]
        beta_h = h * world_contact_beta[w]
        for p in range(plane_first[w], plane_first[w + 1]):
            n = plane_normal[p]
            point = plane_point[p]
            if wp.dot(x - point, n) < eps:
                phi = plane_distance(x, point, n, plane_hole_center[p], plane_hole_radius[p])
                v_surface = surface_velocity(x, plane_motion[p], motion_center_now, motion_velocity_step, motion_spin)
                x, v = resolve_moving(x, v, qd_prev[i], n, v_surface, phi, n, plane_restitution[p],
                                      plane_friction[p], eps, eps_v, rest_steps, beta_h, stage)
        q_out[i] = x
        qd_out[i] = v


@both_precisions
@wp.kernel
def collide_moving_bowls(
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    bowl_first: wp.array(dtype=wp.int32),
    bowl_center: wp.array(dtype=vec3),
    bowl_radius: wp.array(dtype=Float),
    bowl_cut_height: wp.array(dtype=Float),
    bowl_restitution: wp.array(dtype=Float),
    bowl_friction: wp.array(dtype=Float),
    bowl_motion: wp.array(dtype=wp.int32),
    motion_center_now: wp.array(dtype=vec3),
    motion_turn_now: wp.array(dtype=vec3),
    motion_velocity_step: wp.array(dtype=vec3),
    motion_point_prev: wp.array(dtype=vec3),
    motion_spin: wp.array(dtype=vec3),
    motion_rest_point: wp.array(dtype=vec3),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    h: Float,
    world_contact_beta: wp.array(dtype=Float),
    stage: int,
    q_prev: wp.array(dtype=vec3),
    qd_prev: wp.array(dtype=vec3),
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    if particle_inv_mass[i] != type(h)(0.0):
        w = particle_world[i]
        x = q_out[i]
        v = qd_out[i]
        beta_h = h * world_contact_beta[w]
        for b in range(bowl_first[w], bowl_first[w + 1]):
            c = bowl_center[b]
            radius = bowl_radius[b]
            m = bowl_motion[b]
            # Whether the bowl held the particle is asked of the bowl where it was then.
            c_prev = c
            if m >= 0:
                c_prev = motion_point_prev[m]
            holds, n_out = bowl_holds(q_prev[i], c_prev, radius, eps)
            if holds:
                phi, n = moving_bowl_distance(x, c, radius, bowl_cut_height[b], m, motion_turn_now, motion_rest_point)
                v_surface = surface_velocity(x, m, motion_center_now, motion_velocity_step, motion_spin)
                x, v = resolve_moving(x, v, qd_prev[i], -n_out, v_surface, phi, n, bowl_restitution[b],
                                      bowl_friction[b], eps, eps_v, rest_steps, beta_h, stage)
        q_out[i] = x
        qd_out[i] = v


@both_precisions
@wp.kernel
def collide_moving_spheres(
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    sphere_first: wp.array(dtype=wp.int32),
    sphere_center: wp.array(dtype=vec3),
    sphere_radius: wp.array(dtype=Float),
    sphere_restitution: wp.array(dtype=Float),
    sphere_friction: wp.array(dtype=Float),
    sphere_motion: wp.array(dtype=wp.int32),
    motion_center_now: wp.array(dtype=vec3),
    motion_turn_now: wp.array(dtype=vec3),
    motion_velocity_step: wp.array(dtype=vec3),
    motion_point_prev: wp.array(dtype=vec3),
    motion_spin: wp.array(dtype=vec3),
    motion_rest_point: wp.array(dtype=vec3),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    h: Float,
    world_contact_beta: wp.array(dtype=Float),
    stage: int,
    q_prev: wp.array(dtype=vec3),
    qd_prev: wp.array(dtype=vec3),
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    if particle_inv_mass[i] != type(h)(0.0):
        w = particle_world[i]
        x = q_out[i]
        v = qd_out[i]
        beta_h = h * world_contact_beta[w]
        for s in range(sphere_first[w], sphere_first[w + 1]):
            c = sphere_center[s]
            radius = sphere_radius[s]
            m = sphere_motion[s]
            c_prev = c
            if m >= 0:
                c_prev = motion_point_prev[m]
            phi, n = sphere_distance(x, c, radius)
            _phi_prev, n_prev = sphere_distance(q_prev[i], c_prev, radius)
            v_surface = surface_velocity(x, m, motion_center_now, motion_velocity_step, motion_spin)
            x, v = resolve_moving(x, v, qd_prev[i], n_prev, v_surface, phi, n, sphere_restitution[s],
                                  sphere_friction[s], eps, eps_v, rest_steps, beta_h, stage)
        q_out[i] = x
        qd_out[i] = v

"""Terrain contact: collision with restitution, resting contact and Coulomb friction.

Contact runs once per step, after the integrator has advanced the smooth forces (springs and
gravity) from y_n to y*. Runge-Kutta stages assume a smooth right-hand side; applying impulses to
trial states (as the original program did inside every force evaluation) changes stage states
that the method later combines, so midpoint and RK4 lose their meaning and can inject energy.
Splitting contact off keeps every integrator's smooth part exact in its order and treats all of
them alike at impacts, where every method is first order anyway.

``resolve_contact`` is shared by every primitive: a primitive only supplies the signed distance
and the outward normal at the particle.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


def build(scalar):
    vec3 = wp.types.vector(3, scalar)

    @wp.func
    def resolve_contact(
        x: vec3,
        v: vec3,
        v_prev: vec3,
        phi: scalar,
        phi_prev: scalar,
        normal: vec3,
        restitution: scalar,
        friction: scalar,
        eps: scalar,
        eps_v: scalar,
        beta_h: scalar,
    ):
        """Contact response of one particle against one surface; returns the new (x, v).

        phi and phi_prev are the signed distances after and before the step (positive outside),
        v_prev the velocity before the step; v - v_prev is the step's impulse per unit mass, h f/m.
        beta_h is h times the integrator's position gain for a constant force over the step
        (dx = beta h dv: 0 explicit Euler, 1/2 midpoint and RK4, 1 symplectic and implicit Euler).
        """
        if phi >= eps:
            return x, v
        vn = wp.dot(normal, v)
        dvn = wp.dot(normal, v - v_prev)
        resting = phi_prev < eps and wp.abs(wp.dot(normal, v_prev)) < eps_v and dvn < scalar(0.0)
        if resting:
            # Cancel the normal part of the force (the particle stays on the surface) and let
            # Coulomb friction remove at most mu |N.f| h / m of tangential speed, never reversing it.
            vt = v - vn * normal
            speed = wp.length(vt)
            budget = friction * (-dvn)
            v_new = vec3(scalar(0.0))
            if speed > budget:
                v_new = vt * ((speed - budget) / speed)
            # Resting contact and friction act as forces over the whole step: move the position by
            # what the integrator would have made of them, so a stuck particle does not creep.
            dv = v_new - v
            x = x + beta_h * dv
            phi = phi + beta_h * wp.dot(normal, dv)
            v = v_new
        elif vn < scalar(0.0):
            # Collision: reflect the approaching normal velocity, keep the tangential part.
            v = v - (scalar(1.0) + restitution) * vn * normal
        if phi < scalar(0.0):
            x = x - phi * normal
        return x, v

    @wp.func
    def plane_distance(x: vec3, point: vec3, normal: vec3, hole_center: vec3, hole_radius: scalar):
        """Signed distance to a plane; a huge value over its hole, where the plane does not collide."""
        phi = wp.dot(x - point, normal)
        if hole_radius > scalar(0.0):
            r = x - hole_center
            r = r - wp.dot(r, normal) * normal
            if wp.length_sq(r) < hole_radius * hole_radius:
                return scalar(1.0e30)
        return phi

    @wp.kernel(module="unique")
    def collide_planes(
        # Model:
        particle_inv_mass: wp.array(dtype=scalar),
        particle_world: wp.array(dtype=wp.int32),
        plane_count: int,
        plane_world: wp.array(dtype=wp.int32),
        plane_point: wp.array(dtype=vec3),
        plane_normal: wp.array(dtype=vec3),
        plane_hole_center: wp.array(dtype=vec3),
        plane_hole_radius: wp.array(dtype=scalar),
        plane_restitution: wp.array(dtype=scalar),
        plane_friction: wp.array(dtype=scalar),
        eps: scalar,
        eps_v: scalar,
        h: scalar,
        world_contact_beta: wp.array(dtype=scalar),
        # State before the step:
        q_prev: wp.array(dtype=vec3),
        qd_prev: wp.array(dtype=vec3),
        # State after the step, corrected in place (each thread touches only its own particle):
        q_out: wp.array(dtype=vec3),
        qd_out: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        if particle_inv_mass[i] == scalar(0.0):
            return
        w = particle_world[i]
        x = q_out[i]
        v = qd_out[i]
        x_prev = q_prev[i]
        v_prev = qd_prev[i]
        for p in range(plane_count):
            if plane_world[p] != w:
                continue
            n = plane_normal[p]
            point = plane_point[p]
            hc = plane_hole_center[p]
            hr = plane_hole_radius[p]
            phi = plane_distance(x, point, n, hc, hr)
            phi_prev = plane_distance(x_prev, point, n, hc, hr)
            x, v = resolve_contact(
                x,
                v,
                v_prev,
                phi,
                phi_prev,
                n,
                plane_restitution[p],
                plane_friction[p],
                eps,
                eps_v,
                h * world_contact_beta[w],
            )
        q_out[i] = x
        qd_out[i] = v

    return {
        "resolve_contact": resolve_contact,
        "plane_distance": plane_distance,
        "collide_planes": collide_planes,
    }

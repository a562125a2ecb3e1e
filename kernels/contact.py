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
        # A resting particle that still moves away after the step (vn >= 0; on a convex surface the
        # tangent of the last step points outward by |v| h / R) is separating: the surface pushes
        # nothing, so neither normal cancellation nor friction applies. Cancelling it instead would
        # glue particles to a sphere well past the point where they fly off.
        if resting and vn < scalar(0.0):
            # Cancel the normal velocity (the particle stays on the surface) and let Coulomb
            # friction remove at most mu times that normal impulse per unit mass, -vn, of
            # tangential speed, never reversing it. On a flat surface -vn = |N.f| h / m; on a
            # curved one it also holds the centripetal part m |v|^2 h / R of the normal force.
            vt = v - vn * normal
            speed = wp.length(vt)
            budget = friction * (-vn)
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

    @wp.func
    def contact_planes(
        x: vec3,
        v: vec3,
        x_prev: vec3,
        v_prev: vec3,
        w: int,
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
        beta_h: scalar,
    ):
        """One particle of world ``w`` against every plane of that world; returns the new (x, v).

        Shared by ``collide_planes`` and the fused last stage of the lattice path.
        """
        for p in range(plane_count):
            if plane_world[p] == w:
                n = plane_normal[p]
                point = plane_point[p]
                hc = plane_hole_center[p]
                hr = plane_hole_radius[p]
                phi = plane_distance(x, point, n, hc, hr)
                phi_prev = plane_distance(x_prev, point, n, hc, hr)
                x, v = resolve_contact(
                    x, v, v_prev, phi, phi_prev, n, plane_restitution[p], plane_friction[p], eps, eps_v, beta_h
                )
        return x, v

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
        x, v = contact_planes(
            q_out[i],
            qd_out[i],
            q_prev[i],
            qd_prev[i],
            w,
            plane_count,
            plane_world,
            plane_point,
            plane_normal,
            plane_hole_center,
            plane_hole_radius,
            plane_restitution,
            plane_friction,
            eps,
            eps_v,
            h * world_contact_beta[w],
        )
        q_out[i] = x
        qd_out[i] = v

    # -- Bowls and spheres ----------------------------------------------------------------------
    # Curved primitives give resolve_contact the distance and normal at the particle itself; a
    # step's straight move leaves a curved surface by O(|v|^2 h^2 / R), which the position
    # correction takes back, so a particle sliding along the surface follows the curve.

    @wp.func
    def bowl_distance(x: vec3, center: vec3, radius: scalar, cut_height: scalar):
        """Signed distance to a bowl (inside of a sphere where y < cut_height), positive inside.

        Returns (phi, inward normal); phi is a huge value at or above the cut, where the bowl does
        not exist.
        """
        d = center - x
        r = wp.length(d)
        n = vec3(scalar(0.0), scalar(1.0), scalar(0.0))
        if r > scalar(0.0):
            n = d / r
        if x[1] >= cut_height:
            return scalar(1.0e30), n
        return radius - r, n

    @wp.func
    def sphere_distance(x: vec3, center: vec3, radius: scalar):
        """Signed distance to a solid sphere, positive outside; returns (phi, outward normal)."""
        d = x - center
        r = wp.length(d)
        # At the centre every direction is as good; push up, where the particle is most likely from.
        n = vec3(scalar(0.0), scalar(1.0), scalar(0.0))
        if r > scalar(0.0):
            n = d / r
        return r - radius, n

    @wp.kernel(module="unique")
    def collide_bowls(
        # Model:
        particle_inv_mass: wp.array(dtype=scalar),
        particle_world: wp.array(dtype=wp.int32),
        bowl_count: int,
        bowl_world: wp.array(dtype=wp.int32),
        bowl_center: wp.array(dtype=vec3),
        bowl_radius: wp.array(dtype=scalar),
        bowl_cut_height: wp.array(dtype=scalar),
        bowl_restitution: wp.array(dtype=scalar),
        bowl_friction: wp.array(dtype=scalar),
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
        for b in range(bowl_count):
            if bowl_world[b] != w:
                continue
            c = bowl_center[b]
            radius = bowl_radius[b]
            # The bowl holds what is inside it: a particle that began the step outside the sphere
            # (beyond the contact layer and float rounding of a corrected position) is behind the
            # shell and passes, instead of being pulled through the wall to the inside.
            phi_prev, n_prev = sphere_distance(x_prev, c, radius)
            if phi_prev > eps + radius * scalar(1.0e-4):
                continue
            phi, n = bowl_distance(x, c, radius, bowl_cut_height[b])
            x, v = resolve_contact(
                x,
                v,
                v_prev,
                phi,
                -phi_prev,
                n,
                bowl_restitution[b],
                bowl_friction[b],
                eps,
                eps_v,
                h * world_contact_beta[w],
            )
        q_out[i] = x
        qd_out[i] = v

    @wp.kernel(module="unique")
    def collide_spheres(
        # Model:
        particle_inv_mass: wp.array(dtype=scalar),
        particle_world: wp.array(dtype=wp.int32),
        sphere_count: int,
        sphere_world: wp.array(dtype=wp.int32),
        sphere_center: wp.array(dtype=vec3),
        sphere_radius: wp.array(dtype=scalar),
        sphere_restitution: wp.array(dtype=scalar),
        sphere_friction: wp.array(dtype=scalar),
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
        for s in range(sphere_count):
            if sphere_world[s] != w:
                continue
            c = sphere_center[s]
            radius = sphere_radius[s]
            phi, n = sphere_distance(x, c, radius)
            phi_prev, n_prev = sphere_distance(x_prev, c, radius)
            x, v = resolve_contact(
                x,
                v,
                v_prev,
                phi,
                phi_prev,
                n,
                sphere_restitution[s],
                sphere_friction[s],
                eps,
                eps_v,
                h * world_contact_beta[w],
            )
        q_out[i] = x
        qd_out[i] = v

    return {
        "resolve_contact": resolve_contact,
        "plane_distance": plane_distance,
        "contact_planes": contact_planes,
        "collide_planes": collide_planes,
        "bowl_distance": bowl_distance,
        "sphere_distance": sphere_distance,
        "collide_bowls": collide_bowls,
        "collide_spheres": collide_spheres,
    }

"""Triangle-mesh terrain and mesh voxelisation, through Warp's BVH queries (``wp.Mesh``).

Contact with a mesh gives ``resolve_contact`` (kernels/contact.py) the same two things an analytic
primitive does: the signed distance at the particle and the outward normal there. The BVH finds the
closest triangle (in float32, as ``wp.Mesh`` stores it); the distance is then measured in the
model's precision from that triangle's own vertices: over a face's interior it is the distance to
the face's plane, so a flat mesh gives exactly what an analytic plane gives; over an edge or a vertex
it is the distance to the closest point, signed by the winding number (closed meshes) or by the side
the face's normal points to (open sheets, which collide from that side only).
"""

import functools

import warp as wp

from . import contact, springs

wp.set_module_options({"enable_backward": False})


# Voxelisation does not depend on the model's precision: one kernel, in float32 as wp.Mesh is.
@wp.kernel(module="unique")
def mark_inside_mesh(
    mesh: wp.uint64,
    origin: wp.vec3,
    spacing: wp.vec3,
    shape: wp.vec3i,
    on_surface: float,
    threshold: float,
    # out: 1 where the lattice point lies inside the mesh (generalized winding number above
    # ``threshold``, 1/2 for the inside) or within ``on_surface`` of it (a box mesh's faces hold
    # lattice points)
    inside_out: wp.array(dtype=wp.int32),
):
    k = wp.tid()
    nz = shape[2]
    ny = shape[1]
    iz = k % nz
    iy = (k // nz) % ny
    ix = k // (nz * ny)
    p = origin + wp.cw_mul(spacing, wp.vec3(float(ix), float(iy), float(iz)))
    # The whole mesh is within reach: the winding number needs no distance bound.
    q = wp.mesh_query_point_sign_winding_number(mesh, p, 1.0e30, 2.0, threshold)
    inside = 0
    if q.result:
        if q.sign < 0.0:
            inside = 1
        elif wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v)) <= on_surface:
            inside = 1
    inside_out[k] = inside


@functools.cache
def build(scalar):
    vec3 = wp.types.vector(3, scalar)
    resolve_contact = contact.build(scalar)["resolve_contact"]
    spring_force = springs.build(scalar)["spring_force"]

    @wp.func
    def closest_on_triangle(p: vec3, a: vec3, b: vec3, c: vec3):
        """Closest point of triangle (a, b, c) to p (Ericson, Real-Time Collision Detection, 5.1.5)."""
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = wp.dot(ab, ap)
        d2 = wp.dot(ac, ap)
        if d1 <= scalar(0.0) and d2 <= scalar(0.0):
            return a
        bp = p - b
        d3 = wp.dot(ab, bp)
        d4 = wp.dot(ac, bp)
        if d3 >= scalar(0.0) and d4 <= d3:
            return b
        vc = d1 * d4 - d3 * d2
        if vc <= scalar(0.0) and d1 >= scalar(0.0) and d3 <= scalar(0.0):
            return a + ab * (d1 / (d1 - d3))
        cp = p - c
        d5 = wp.dot(ab, cp)
        d6 = wp.dot(ac, cp)
        if d6 >= scalar(0.0) and d5 <= d6:
            return c
        vb = d5 * d2 - d1 * d6
        if vb <= scalar(0.0) and d2 >= scalar(0.0) and d6 <= scalar(0.0):
            return a + ac * (d2 / (d2 - d6))
        va = d3 * d6 - d5 * d4
        if va <= scalar(0.0) and (d4 - d3) >= scalar(0.0) and (d5 - d6) >= scalar(0.0):
            return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        denom = scalar(1.0) / (va + vb + vc)
        return a + ab * (vb * denom) + ac * (vc * denom)

    @wp.func
    def mesh_distance(
        x: vec3,
        mesh: wp.uint64,
        closed: int,
        reach: scalar,
        tri_start: int,
        mesh_tris: wp.array(dtype=wp.vec3i),
        mesh_points: wp.array(dtype=vec3),
    ):
        """Signed distance (positive outside / in front) and outward normal of a mesh at x:
        (phi, normal). phi is a huge value farther than ``reach`` from every face."""
        xf = wp.vec3(wp.float32(x[0]), wp.float32(x[1]), wp.float32(x[2]))
        q = wp.mesh_query_point_no_sign(mesh, xf, wp.float32(reach))
        if closed != 0:
            q = wp.mesh_query_point_sign_winding_number(mesh, xf, wp.float32(reach))
        up = vec3(scalar(0.0), scalar(1.0), scalar(0.0))
        if not q.result:
            return scalar(1.0e30), up
        t = mesh_tris[tri_start + q.face]
        a = mesh_points[t[0]]
        b = mesh_points[t[1]]
        c = mesh_points[t[2]]
        nf = wp.cross(b - a, c - a)
        area2 = wp.length(nf)
        if area2 > scalar(0.0):
            nf = nf / area2
        # Over the face, its edges included (the point's projection on the face's plane inside the
        # triangle, to a relative 1e-5 of its size, far above rounding): the distance to the face's
        # plane, as an analytic plane measures it. The BVH's float32 barycentrics only chose the face.
        phi = wp.dot(x - a, nf)
        pp = x - phi * nf
        tol = -scalar(1.0e-5) * area2
        if (
            wp.dot(wp.cross(b - a, pp - a), nf) >= tol
            and wp.dot(wp.cross(c - b, pp - b), nf) >= tol
            and wp.dot(wp.cross(a - c, pp - c), nf) >= tol
        ):
            return phi, nf
        d = x - closest_on_triangle(x, a, b, c)
        dist = wp.length(d)
        if dist == scalar(0.0):
            return scalar(0.0), nf
        # Beside an edge or a vertex: the distance to the closest point, signed.
        side = scalar(1.0)
        if closed != 0:
            if q.sign < wp.float32(0.0):
                side = scalar(-1.0)
        elif wp.dot(d, nf) < scalar(0.0):
            side = scalar(-1.0)
        return side * dist, d * (side / dist)

    @wp.kernel(module="unique")
    def collide_meshes(
        # Model:
        particle_inv_mass: wp.array(dtype=scalar),
        particle_world: wp.array(dtype=wp.int32),
        mesh_first: wp.array(dtype=wp.int32),
        mesh_id: wp.array(dtype=wp.uint64),
        mesh_closed: wp.array(dtype=wp.int32),
        mesh_reach: wp.array(dtype=scalar),
        mesh_tri_start: wp.array(dtype=wp.int32),
        mesh_tris: wp.array(dtype=wp.vec3i),
        mesh_points: wp.array(dtype=vec3),
        mesh_restitution: wp.array(dtype=scalar),
        mesh_friction: wp.array(dtype=scalar),
        eps: scalar,
        eps_v: scalar,
        rest_steps: scalar,
        h: scalar,
        world_contact_beta: wp.array(dtype=scalar),
        stage: int,
        # State before the step:
        q_prev: wp.array(dtype=vec3),
        qd_prev: wp.array(dtype=vec3),
        # State after the step, corrected in place:
        q_out: wp.array(dtype=vec3),
        qd_out: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        if particle_inv_mass[i] != scalar(0.0):
            w = particle_world[i]
            x = q_out[i]
            v = qd_out[i]
            # The meshes of world w are mesh_first[w] .. mesh_first[w + 1] - 1 (sorted by world).
            for m in range(mesh_first[w], mesh_first[w + 1]):
                phi, n = mesh_distance(x, mesh_id[m], mesh_closed[m], mesh_reach[m], mesh_tri_start[m], mesh_tris, mesh_points)
                if phi < eps:
                    x, v = resolve_contact(
                        x,
                        v,
                        wp.dot(n, qd_prev[i]),
                        phi,
                        n,
                        mesh_restitution[m],
                        mesh_friction[m],
                        eps,
                        eps_v,
                        rest_steps,
                        h * world_contact_beta[w],
                        stage,
                    )
            q_out[i] = x
            qd_out[i] = v

    # -- Masked lattices (mesh jellies): the lattice stencil over the points that exist -----------

    @wp.func
    def masked_neighbour(i: int, ok: bool, cell: int, offset: int, grid_start: int, grid: wp.array(dtype=wp.int32)):
        """The particle at lattice index cell + offset, or i itself (zero force) when the offset is
        off the lattice (``ok`` false) or the point is not in the jelly (grid entry -1)."""
        p = grid[grid_start + wp.where(ok, cell + offset, cell)]
        return wp.where(p < 0, i, p)

    @wp.kernel(module="unique")
    def eval_masked_springs(
        # Model:
        particle_jelly: wp.array(dtype=wp.int32),
        particle_cell: wp.array(dtype=wp.int32),
        jelly_shape: wp.array(dtype=wp.vec3i),
        jelly_grid_start: wp.array(dtype=wp.int32),
        grid: wp.array(dtype=wp.int32),
        jelly_types: wp.array(dtype=wp.int32),
        jelly_rest: wp.array2d(dtype=scalar),
        jelly_ks: wp.array2d(dtype=scalar),
        jelly_kd: wp.array2d(dtype=scalar),
        # State in:
        q: wp.array(dtype=vec3),
        qd: wp.array(dtype=vec3),
        # Out (every element written):
        f_out: wp.array(dtype=vec3),
    ):
        # One thread per particle gathers the stencil springs to its present neighbours (as the
        # lattice path's gather_lattice_force, with the neighbour looked up in the jelly's grid of
        # particle indices): no atomics, a fixed order, so deterministic.
        i = wp.tid()
        j = particle_jelly[i]
        shape = jelly_shape[j]
        cell = particle_cell[i]
        gs = jelly_grid_start[j]
        c = cell % shape[2]
        t = cell // shape[2]
        b = t % shape[1]
        a = t // shape[1]
        row = shape[1] * shape[2]
        types = jelly_types[j]
        x = q[i]
        v = qd[i]
        f = vec3(scalar(0.0))
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    m = wp.abs(di) + wp.abs(dj) + wp.abs(dk)
                    if m > 0:
                        ty = wp.min(m - 1, 1)  # one nonzero component: structural, else shear
                        ok = ((types >> ty) & 1) != 0
                        ok = ok and a + di >= 0 and a + di < shape[0] and b + dj >= 0 and b + dj < shape[1]
                        ok = ok and c + dk >= 0 and c + dk < shape[2]
                        p = masked_neighbour(i, ok, cell, di * row + dj * shape[2] + dk, gs, grid)
                        rest = jelly_rest[j, (di + 1) * 9 + (dj + 1) * 3 + dk + 1]
                        f += spring_force(x, q[p], v, qd[p], rest, jelly_ks[j, ty], jelly_kd[j, ty])
        if ((types >> 2) & 1) != 0:
            for axis in range(3):
                for side in range(2):
                    o = wp.vec3i(0, 0, 0)
                    o[axis] = 4 * side - 2
                    ok = a + o[0] >= 0 and a + o[0] < shape[0] and b + o[1] >= 0 and b + o[1] < shape[1]
                    ok = ok and c + o[2] >= 0 and c + o[2] < shape[2]
                    p = masked_neighbour(i, ok, cell, o[0] * row + o[1] * shape[2] + o[2], gs, grid)
                    rest = jelly_rest[j, 27 + axis]
                    f += spring_force(x, q[p], v, qd[p], rest, jelly_ks[j, 2], jelly_kd[j, 2])
        f_out[i] = f

    return {"masked_neighbour": masked_neighbour, "eval_masked_springs": eval_masked_springs,
            "closest_on_triangle": closest_on_triangle, "mesh_distance": mesh_distance, "collide_meshes": collide_meshes, "mark_inside_mesh": mark_inside_mesh}

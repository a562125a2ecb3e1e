"""Terrain contact of a step: the post-step response and the Runge-Kutta stage filter.

One launch per terrain primitive type the model has (planes, bowls, spheres); a scene without a
bowl launches no bowl kernel. The kernels are in ``kernels/contact.py``, which explains why contact
is applied once per step on the result rather than inside the stages.
"""

from __future__ import annotations

import itertools

import numpy as np
import warp as wp

from ..kernels.contact import LAYER_TOUCH
from .mesh_terrain import animate_meshes, mesh_arrays, mesh_moves, moving_mesh_arrays
from .pins import motion_transform, path_position
from ..kernels import contact as contact_kernels
from ..kernels import mesh as mesh_kernels

# The kinds of terrain that move (``kernels/contact.py`` ``move_terrain``'s motion_kind).
MOVING_KINDS = ("plane", "bowl", "sphere", "mesh")


def terrain_items(model, kind: str) -> list:
    """The host list of a model's terrain of ``kind`` (one of :data:`MOVING_KINDS`)."""
    return model.meshes if kind == "mesh" else getattr(model, kind + "s")


def terrain_at(item: dict, t: float) -> dict:
    """A terrain primitive (a plane's, bowl's or sphere's dict of ``ModelBuilder``) where its motion
    has carried it at ``t`` [s], float64 on the host: its points (``point``, ``hole_center``,
    ``center``) and ``normal`` through the motion's rigid map; the item itself when it does not move."""
    motion = item.get("motion")
    if motion is None:
        return item
    rot, shift = motion_transform(motion, t)
    out = dict(item)
    for key in ("point", "hole_center", "center"):
        if key in item:
            out[key] = rot @ np.asarray(item[key], dtype=np.float64) + shift
    if "normal" in item:
        out["normal"] = rot @ np.asarray(item["normal"], dtype=np.float64)
    return out


class TerrainMotion:
    """Device arrays of the moving planes, bowls, spheres and meshes of a model (``Model.terrain_motion``).

    Per kind an index per primitive into the moving ones (``plane_motion`` ...; -1: static), and
    per moving primitive its geometry as given and its motion (a pin's, ``kernels/pins.py``). What
    ``move_terrain`` writes at every step's start is each run's own (:class:`TerrainPoses`).
    """

    @classmethod
    def of(cls, model, device, scalar, vec3):
        """The moving terrain of a finalized ``model`` (its host lists ``planes``, ``bowls``,
        ``spheres``), or None when nothing moves: a static scene has no motion arrays at all."""
        items = [(k, i, it) for k, name in enumerate(MOVING_KINDS) for i, it in enumerate(terrain_items(model, name))
                 if it.get("motion") is not None]
        return cls(model, items, device, scalar, vec3) if items else None

    def __init__(self, model, items, device, scalar, vec3):
        np_scalar = np.float64 if scalar == wp.float64 else np.float32

        def arr(values, dtype, np_dtype):
            return wp.array(np.asarray(values, dtype=np_dtype), dtype=dtype, device=device)

        def vecs(values):
            return arr(np.reshape(values, (-1, 3)), vec3, np_scalar)

        self.count = len(items)
        for k, name in enumerate(MOVING_KINDS):
            index = np.full(len(terrain_items(model, name)), -1, dtype=np.int32)
            for m, (kind, i, _it) in enumerate(items):
                if kind == k:
                    index[i] = m
            setattr(model, f"{name}_motion", arr(index, wp.int32, np.int32))
        motions = [it["motion"] for _k, _i, it in items]
        key_first, key_t, key_v = [], [], []
        for mo in motions:
            key_first.append(len(key_t))
            key_t.extend(mo["key_times"])
            key_v.extend(mo["key_offsets"])
        self.kind = arr([k for k, _i, _it in items], wp.int32, np.int32)
        self.item = arr([i for _k, i, _it in items], wp.int32, np.int32)
        # A mesh's reference point is its motion's centre (move_terrain moves no mesh geometry).
        self.rest_point = vecs([it.get("point", it.get("center", it["motion"]["center"])) for _k, _i, it in items])
        self.rest_normal = vecs([it.get("normal", np.zeros(3)) for _k, _i, it in items])
        self.rest_hole = vecs([it.get("hole_center", np.zeros(3)) for _k, _i, it in items])
        self.velocity = vecs([mo["velocity"] for mo in motions])
        self.spin = vecs([mo["spin"] for mo in motions])
        self.center = vecs([mo["center"] for mo in motions])
        self.key_first = arr(key_first, wp.int32, np.int32)
        self.key_count = arr([len(mo["key_times"]) for mo in motions], wp.int32, np.int32)
        self.smooth = arr([int(mo["interpolation"] == "smooth") for mo in motions], wp.int32, np.int32)
        self.key_time = arr(key_t or [0.0], scalar, np_scalar)
        self.key_value = vecs(key_v or [0.0, 0.0, 0.0])

    def contact_arrays(self, kind_motion, poses) -> tuple:
        """What a ``collide_moving_*`` kernel takes after its kind's arrays (``poses``: a run's
        :class:`TerrainPoses`)."""
        return (kind_motion, poses.center_now, poses.turn_now, poses.velocity_step, poses.point_prev, self.spin,
                self.rest_point)


class TerrainPoses:
    """The terrain where one run has it (part of :class:`~softsim_warp.core.model.RunState`).

    With moving terrain: the run's own copies of the geometry that moves (``plane_point``,
    ``plane_normal``, ``plane_hole_center``, ``bowl_center``, ``sphere_center``, at t = 0 when
    made), which ``move_terrain`` sets at every step's start to the pose at the step's end, with
    per moving primitive its motion's centre and turn there (``center_now``, ``turn_now``, vec3),
    the centre's velocity over the step (``velocity_step``), its reference point at the step's
    start (``point_prev``), and the terrain clock (steps taken, shape [1], int32). Without moving
    terrain the geometry is the model's arrays, which nothing writes, and the rest None.
    """

    def __init__(self, model):
        tm = model.terrain_motion
        moving = tm is not None
        for name in ("plane_point", "plane_normal", "plane_hole_center", "bowl_center", "sphere_center"):
            array = getattr(model, name)
            setattr(self, name, wp.clone(array) if moving else array)
        self.clock = self.center_now = self.turn_now = self.velocity_step = self.point_prev = None
        if not moving:
            return
        device, vec3 = model.device, model.vec3
        self.center_now = wp.zeros(tm.count, dtype=vec3, device=device)
        self.turn_now = wp.zeros(tm.count, dtype=vec3, device=device)
        self.velocity_step = wp.zeros(tm.count, dtype=vec3, device=device)
        self.point_prev = wp.zeros(tm.count, dtype=vec3, device=device)
        self.clock = wp.zeros(1, dtype=wp.int32, device=device)

    def reset(self):
        """Restart the terrain clock at t = 0."""
        if self.clock is not None:
            self.clock.zero_()


def terrain_speed(model, reach: float) -> float:
    """Largest speed [m/s] of a moving plane's, bowl's, sphere's or mesh's surface within ``reach``
    [m] of its motion's centre, on the host: its velocity, its keyframed offset's speed (sampled, 64
    points a segment, which the smooth spline's overshoot between keys needs) and its spin times
    the reach, plus an animated mesh's fastest vertex between its samples. 0 without moving terrain."""
    fastest = 0.0
    for kind in MOVING_KINDS:
        for it in terrain_items(model, kind):
            motion = it.get("motion")
            if motion is None:
                continue
            times = np.asarray(motion["key_times"], dtype=np.float64)
            keyed = 0.0
            if times.size > 1:
                t = np.concatenate([np.linspace(a, b, 65) for a, b in itertools.pairwise(times)])
                still = dict(motion, velocity=np.zeros(3), spin=np.zeros(3))
                d = np.array([path_position(still, np.zeros(3), s) for s in t])
                dt = np.diff(t)
                keyed = float((np.linalg.norm(np.diff(d, axis=0), axis=1)[dt > 0] / dt[dt > 0]).max())
            speed = np.linalg.norm(motion["velocity"]) + keyed + np.linalg.norm(motion["spin"]) * reach
            fastest = max(fastest, float(speed))
    for it in terrain_items(model, "mesh"):  # an animated mesh: its fastest vertex between samples
        if it.get("samples") is not None:
            times, points = it["samples"]
            step = np.linalg.norm(np.diff(points, axis=0), axis=2).max(axis=1) / np.diff(times)
            # (A rigid motion of the same mesh adds its speed; the loop above counted it.)
            fastest = max(fastest, float(step.max()))
    return fastest


def move_terrain(model, run, dt):
    """Put the moving terrain of ``run`` (a ``RunState``) where it is at the end of the step about
    to be taken (one launch, which also advances the terrain clock, and for animated meshes what
    ``animate_meshes`` does); nothing without moving terrain."""
    animate_meshes(model, run, dt)
    tm = model.terrain_motion
    if tm is None:
        return
    poses = run.terrain
    wp.launch(
        contact_kernels.move_terrain,
        dim=1,
        inputs=[poses.clock, model.scalar(dt), tm.kind, tm.item, tm.rest_point, tm.rest_normal, tm.rest_hole,
                tm.velocity, tm.spin, tm.center, tm.key_first, tm.key_count, tm.smooth, tm.key_time, tm.key_value],
        outputs=[poses.center_now, poses.turn_now, poses.velocity_step, poses.point_prev, poses.plane_point,
                 poses.plane_normal, poses.plane_hole_center, poses.bowl_center, poses.sphere_center],
        device=model.device,
    )


def apply_contacts(
    model: Model,
    run,
    state_in: State,
    state_out: State,
    dt: float,
    world_contact_beta: wp.array,
    planes=True,
    solve_hooks_only=False,
    layer_touch=False,
):
    """Terrain contact on ``state_out`` after a step of ``dt`` from ``state_in``; one launch per primitive type present,
    against the terrain where ``run`` (the integrator's ``RunState``) has it; then ``run``'s contact hooks.

    ``world_contact_beta`` is, per world, the integrator's position gain for a force held constant
    over the step (x_{n+1} gains beta h^2 a): resting contact and friction shift positions by it.
    ``planes=False`` skips the planes (a fused lattice stage has already applied them).
    ``solve_hooks_only`` runs only the hooks whose ``in_contact_solve`` is true (the default for a
    hook): the implicit contact solve constrains what they change, while a hook that conserves
    momentum pair by pair (jelly contact) runs only after the step. ``layer_touch``: a particle
    touches anywhere within ``contact_epsilon`` (``kernels.contact.LAYER_TOUCH``; the implicit
    integrator's response on its free result), not only once its step has reached the surface.
    """
    h = model.scalar(dt)
    stage = LAYER_TOUCH if layer_touch else 0
    _launch_contacts(model, run, state_in, state_out.particle_q, state_out.particle_qd, h, world_contact_beta, planes,
                     stage)
    for hook in run.contact_hooks:
        if not solve_hooks_only or getattr(hook, "in_contact_solve", True):
            hook(model, state_in, state_out, h, world_contact_beta)


def filter_stage_contacts(
    model: Model, run, state_in: State, q_s: wp.array, qd_s: wp.array, world_contact_beta: wp.array, planes=True
):
    """Contact on an intermediate Runge-Kutta stage state (q_s, qd_s) = y_n + h c_s k, velocities only.

    Only particles that the contact response would hold (resting contact, not an impact) change:
    their stage velocity loses its approaching normal part and what friction takes of the
    tangential one. Without this, a particle resting on terrain moves into it within the stage
    (the stage state ignores the surface), and the dampers of its springs answer that fictitious
    velocity: at the seed's kd = 60 that takes ~18 % off the normal force that the step's contact
    then sees, but less off the tangential force, so friction holds less than mu and a resting
    jelly creeps (7 mm/s on a 30 degree slope with mu = 0.7 under midpoint, where symplectic Euler,
    one stage at y_n, holds). Impacts and positions are left to the post-step response, so no
    impulse enters a stage state. Contact hooks are not applied here. ``planes=False`` skips the
    planes (a fused lattice stage with contact has filtered them already).
    """
    _launch_contacts(model, run, state_in, q_s, qd_s, model.scalar(0.0), world_contact_beta, planes, 1)


def plane_arrays(model, run) -> tuple:
    """The planes' arrays in the order every plane-contact kernel takes them (``collide_planes``, the
    fused stage), where ``run`` (a ``RunState``) has them."""
    poses = run.terrain
    return (
        model.plane_first,
        poses.plane_point,
        poses.plane_normal,
        poses.plane_hole_center,
        model.plane_hole_radius,
        model.plane_restitution,
        model.plane_friction,
    )


def moves(model, kind: str) -> bool:
    """Whether any terrain primitive of ``kind`` ("plane", "bowl", "sphere") of ``model`` moves."""
    return model.terrain_motion is not None and any(
        it.get("motion") is not None for it in terrain_items(model, kind)
    )


def _launch_contacts(model: Model, run, state_in: State, q_out, qd_out, h, world_contact_beta, planes, stage):
    # (count, kernel, the kind's arrays): every collide_* kernel takes the same arguments around them.
    # A kind with a moving primitive takes its moving variant, which reads the motion arrays too.
    kinds = (
        (
            model.plane_count if planes else 0,
            "plane",
            contact_kernels.collide_planes,
            plane_arrays(model, run),
        ),
        (
            model.bowl_count,
            "bowl",
            contact_kernels.collide_bowls,
            (
                model.bowl_first,
                run.terrain.bowl_center,
                model.bowl_radius,
                model.bowl_cut_height,
                model.bowl_restitution,
                model.bowl_friction,
            ),
        ),
        (
            model.sphere_count,
            "sphere",
            contact_kernels.collide_spheres,
            (
                model.sphere_first,
                run.terrain.sphere_center,
                model.sphere_radius,
                model.sphere_restitution,
                model.sphere_friction,
            ),
        ),
    )
    if model.terrain_motion is not None:
        kinds = tuple(
            (count, kind, getattr(contact_kernels, f"collide_moving_{kind}s"),
             arrays + model.terrain_motion.contact_arrays(getattr(model, f"{kind}_motion"), run.terrain))
            if count and moves(model, kind) else (count, kind, kernel, arrays)
            for count, kind, kernel, arrays in kinds
        )
    if model.mesh_count:  # triangle-mesh terrain (core/mesh_terrain.py)
        if mesh_moves(model):
            kinds += ((model.mesh_count, "mesh", mesh_kernels.collide_moving_meshes,
                       mesh_arrays(model, run) + moving_mesh_arrays(model, run)),)
        else:
            kinds += ((model.mesh_count, "mesh", mesh_kernels.collide_meshes, mesh_arrays(model, run)),)
    for count, _kind, kernel, arrays in kinds:
        if count:
            wp.launch(
                kernel,
                dim=model.particle_count,
                inputs=[
                    model.particle_inv_mass,
                    model.particle_world,
                    *arrays,
                    model.contact_epsilon,
                    model.contact_velocity_epsilon,
                    model.restitution_threshold_steps,
                    h,
                    world_contact_beta,
                    stage,
                    state_in.particle_q,
                    state_in.particle_qd,
                ],
                outputs=[q_out, qd_out],
                device=model.device,
            )

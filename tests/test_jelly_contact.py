"""Contact between jellies and self-contact (core/particle_contact.py, kernels/particle_contact/).

Physics checked against what cannot agree by accident: conservation of linear momentum (every pair
impulse is equal and opposite), the mirror symmetry of a symmetric collision, the rebound from a
plane of restitution 0 (what the springs alone give), Coulomb's law on a slope (a block sticks for
tan(theta) < mu and slides with a = g (sin(theta) - mu cos(theta))), a point-in-lattice test for
interpenetration, and bitwise reproducibility. Small lattices keep every test within seconds on the
CPU.
"""

import copy
import math

import numpy as np
import pytest
import warp as wp

import softsim_warp as ss
from softsim_warp.core import particle_contact
from softsim_warp.core.errors import SceneError
from softsim_warp.core.model import ModelBuilder, populate

SMALL_COLLIDE = ["jelly.0.resolution=5", "jelly.1.resolution=5"]


def _frames(scene, model=None, device="cpu", integrator=None, frames=None, every=1):
    """Positions and velocities (float64 NumPy) at every ``every``-th written frame, frame 0 included."""
    model = model or ss.build_model(scene, device=device)
    stepper = ss.Stepper(model, ss.make_integrator(integrator or scene.sim["integrator"], model), scene.sim["dt"])
    steps = int(round(1.0 / scene.sim["fps"] / scene.sim["dt"]))
    frames = scene.frame_count() if frames is None else frames
    out = []
    for f in range(frames + 1):
        if f:
            stepper.advance(steps)
        if f % every == 0 or f == frames:
            out.append(
                (stepper.state.particle_q.numpy().astype(np.float64), stepper.state.particle_qd.numpy().astype(np.float64))
            )
    return model, out


def _jelly_slices(model):
    return [slice(j.particle_start, j.particle_start + j.particle_count) for j in model.jellies]


# -- which scenes get contact, scene keys -------------------------------------------------------


def test_one_jelly_allocates_nothing():
    """A scene of one jelly without self_contact has no hook and no arrays (jelly_drop's speed does not move)."""
    model = ss.build_model(ss.load_scene("jelly_drop"), device="cpu")
    assert model.contact_hooks == () and model.particle_contact is None
    run = model.run_state()
    assert run.particle_contact is None and run.contact_hooks == []


def test_auto_on_with_two_jellies_and_switches():
    model = ss.build_model(ss.load_scene("collide", SMALL_COLLIDE), device="cpu")
    hook = model.particle_contact
    assert model.contact_hooks == () and hook.between_jellies == 1
    run = model.run_state()
    assert run.contact_hooks == [run.particle_contact] and run.particle_contact.tables is hook
    # Surface particles only: 2 * (5^3 - 3^3).
    assert hook.count == 2 * (125 - 27)
    off = ss.build_model(ss.load_scene("collide", SMALL_COLLIDE + ["simulation.jelly_contact=false"]), device="cpu")
    assert off.particle_contact is None
    # One jelly with self-contact: the hook exists, contact between jellies does not.
    one = ss.build_model(ss.load_scene("jelly_drop", ["jelly.0.self_contact=true", "jelly.0.resolution=4"]), device="cpu")
    assert one.particle_contact.between_jellies == 0 and one.particle_contact.count == 64 - 8


def test_defaults_from_lattice_spacing():
    """Pair distance: one lattice spacing by default (radius half of it), the scene's value when given."""
    model = ss.build_model(ss.load_scene("collide", SMALL_COLLIDE), device="cpu")
    spacing = 0.5 / 4
    assert np.allclose(model.particle_contact.contact_radius.numpy(), spacing / 2)
    assert float(model.particle_contact.friction) == pytest.approx(particle_contact.DEFAULT_FRICTION)
    assert float(model.particle_contact.restitution) == 0.0
    given = ss.build_model(
        ss.load_scene("collide", SMALL_COLLIDE + ["simulation.jelly_contact_thickness=0.2"]), device="cpu"
    )
    assert np.allclose(given.particle_contact.contact_radius.numpy(), 0.1)


@pytest.mark.parametrize(
    "override, key",
    [
        ("simulation.jelly_contact=maybe", "simulation.jelly_contact"),
        ("simulation.jelly_contact=1", "simulation.jelly_contact"),
        ("simulation.jelly_contact_thickness=0", "simulation.jelly_contact_thickness"),
        ("simulation.jelly_contact_friction=-0.1", "simulation.jelly_contact_friction"),
        ("simulation.jelly_contact_restitution=1.5", "simulation.jelly_contact_restitution"),
        ("simulation.jelly_contact_iterations=0", "simulation.jelly_contact_iterations"),
        ("jelly.0.self_contact=yes", "jelly.0.self_contact"),
    ],
)
def test_bad_values_are_scene_errors(override, key):
    with pytest.raises(SceneError) as e:
        ss.load_scene("collide", [override])
    assert f": {key}: " in e.value.line()


def test_overrides_reach_the_model():
    scene = ss.load_scene(
        "collide", SMALL_COLLIDE + ["simulation.jelly_contact_friction=0.25", "simulation.jelly_contact_restitution=0.5"]
    )
    assert scene.sim["jelly_contact"] == "auto"
    model = ss.build_model(scene, device="cpu")
    assert float(model.particle_contact.friction) == 0.25
    assert float(model.particle_contact.restitution) == 0.5


# -- collide ------------------------------------------------------------------------------------


@pytest.mark.parametrize("integrator", ["euler", "symplectic", "midpoint", "rk4", "implicit"])
def test_collide_conserves_momentum_and_separates(integrator):
    """Total linear momentum to 1e-12 of its initial value (float64 round-off; about 3e-15 is
    measured), with every integrator; the jellies bounce apart.

    The velocities are made asymmetric so that the initial momentum is not zero, and the jellies
    slide past each other sideways (0.6 m/s apart in y) so that friction acts: sum_i m_i v_i must
    not change, as every contact impulse is applied to both particles of a pair with opposite signs.
    """
    scene = ss.load_scene(
        "collide",
        SMALL_COLLIDE
        + ["simulation.precision=float64", "jelly.0.velocity=[1.5,0.3,0]", "jelly.1.velocity=[-0.5,-0.3,0]"],
    )
    model, frames = _frames(scene, integrator=integrator, frames=60)
    m = model.particle_mass_host
    a, b = _jelly_slices(model)
    p0 = (m[:, None] * frames[0][1]).sum(0)
    d = 0.5 / 4
    for _, v in frames:
        assert np.abs((m[:, None] * v).sum(0) - p0).max() <= 1e-12 * np.linalg.norm(p0)
    q, v = frames[-1]
    assert q[b, 0].min() - q[a, 0].max() > 2 * d
    assert v[b, 0].mean() - v[a, 0].mean() > 0.5  # separating
    assert v[a, 1].mean() - v[b, 1].mean() < 0.5  # friction slowed the sliding: 0.6 -> 0.26 to 0.27 m/s


def test_collide_mirror_symmetric():
    """The head-on collision of two equal jellies is its own mirror image in x = 0 (float64), and
    they meet without passing: over every frame the closest surfaces come to the pair distance d
    (the position pass projects any overlap out; 1.000003 d is measured)."""
    scene = ss.load_scene("collide", SMALL_COLLIDE + ["simulation.precision=float64"])
    model, frames = _frames(scene, frames=45)
    a, b = _jelly_slices(model)
    d = 0.5 / 4
    closest = min(q[b, 0].min() - q[a, 0].max() for q, _ in frames)
    assert 0.98 * d < closest < 1.02 * d
    n = 5
    i, j, k = np.unravel_index(np.arange(n**3), (n, n, n))
    mirror = np.ravel_multi_index((n - 1 - i, j, k), (n, n, n))  # particle of B that mirrors A's
    flip = np.array([-1.0, 1.0, 1.0])
    for q, v in frames:
        qa, qb = q[a], q[b][mirror]
        assert np.abs(qa - qb * flip).max() < 1e-9
        assert np.abs(v[a] - v[b][mirror] * flip).max() < 1e-9


@pytest.mark.parametrize("restitution", [0.0, 0.5, 1.0])
def test_restitution_between_particles(restitution):
    """Two jellies of one particle each (10 g and 20 g, no springs) meet head-on at a relative speed
    of 1.5 m/s: they part at restitution times that speed, with the momentum they had (zero), to
    rounding. The approach speed before the step decides impact or contact; with a
    restitution of zero it is never computed (store_contact), which the first case covers."""
    builder = ModelBuilder((0.0, 0.0, 0.0))
    springs = {t: {"ks": 1000.0, "kd": 0.0} for t in ("structural", "shear", "bending")}
    builder.add_jelly((1, 1, 1), 0.0, 0.01, springs, center=(-0.03, 0.0, 0.0), velocity=(1.0, 0.0, 0.0))
    builder.add_jelly((1, 1, 1), 0.0, 0.02, springs, center=(0.03, 0.0, 0.0), velocity=(-0.5, 0.0, 0.0))
    builder.jelly_contact = True
    builder.jelly_contact_thickness = 0.05
    builder.jelly_contact_restitution = restitution
    model = builder.finalize("cpu", "float64")
    stepper = ss.Stepper(model, ss.make_integrator("symplectic", model), 1.0e-4)
    stepper.advance(1000)  # they touch after about 67 steps
    v = stepper.state.particle_qd.numpy()[:, 0]
    assert abs((v[1] - v[0]) - restitution * 1.5) < 1e-12
    assert abs(0.01 * v[0] + 0.02 * v[1]) < 1e-15


def test_collide_restitution_zero_rebounds_like_springs_on_a_wall():
    """With restitution 0 the rebound is the springs' own: by symmetry, each jelly meets a wall of
    restitution 0 at x = -d/2 (the surfaces touch at the pair distance d), and it leaves at the
    speed the same jelly leaves that plane with (within 1 %; 0.66 % is measured)."""
    scene = ss.load_scene("collide", SMALL_COLLIDE + ["simulation.precision=float64"])
    model, frames = _frames(scene, frames=60, every=60)
    a = _jelly_slices(model)[0]
    rebound = frames[-1][1][a, 0].mean()
    data = copy.deepcopy(scene.data)
    data["jelly"] = data["jelly"][:1]
    d = 0.5 / 4
    data["plane"] = [{"point": [-d / 2, 0.0, 0.0], "normal": [-1.0, 0.0, 0.0], "restitution": 0.0, "friction": 0.5}]
    _, wall = _frames(ss.scene_from_dict(data), frames=60, every=60)
    wall_rebound = wall[-1][1][:, 0].mean()
    assert rebound < -0.3  # it bounced back
    assert rebound == pytest.approx(wall_rebound, rel=0.01)


# -- interpenetration -----------------------------------------------------------------------------


def _tets(q, shape):
    """The deformed lattice's cells, six tetrahedra each (Kuhn split): vertices, shape [T, 4, 3]."""
    nx, ny, nz = shape
    idx = np.arange(nx * ny * nz).reshape(shape)
    corner = {}
    for c in np.ndindex(2, 2, 2):
        corner[c] = idx[c[0] : nx - 1 + c[0], c[1] : ny - 1 + c[1], c[2] : nz - 1 + c[2]].ravel()
    tets = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        path = [(0, 0, 0)]
        for axis in perm:
            step = list(path[-1])
            step[axis] = 1
            path.append(tuple(step))
        tets.append(np.stack([q[corner[c]] for c in path], axis=1))
    return np.concatenate(tets)


def _inside(points, q, shape):
    """Which points lie strictly inside the deformed lattice ``q`` (inside one of its tetrahedra)."""
    t = _tets(q, shape)
    m = np.stack([t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], t[:, 3] - t[:, 0]], axis=2)  # [T, 3, 3]
    ok = np.abs(np.linalg.det(m)) > 1e-12
    inv = np.linalg.inv(m[ok])
    rel = points[:, None, :] - t[ok][None, :, 0, :]
    bary = np.einsum("tij,ptj->pti", inv, rel)
    inside = (bary > 1e-9).all(axis=2) & (bary.sum(axis=2) < 1 - 1e-9)
    return inside.any(axis=1)


def _no_interpenetration(model, frames):
    """No particle of one jelly strictly inside another jelly's deformed lattice, at any of ``frames``
    (only the particles within a jelly's bounding box can be inside it: the others are not tested)."""
    slices = _jelly_slices(model)
    for q, _ in frames:
        for a, ja in zip(slices, model.jellies):
            others = np.concatenate([q[b] for b in slices if b != a])
            lo, hi = q[a].min(axis=0), q[a].max(axis=0)
            near = others[((others > lo) & (others < hi)).all(axis=1)]
            if len(near):
                assert not _inside(near, q[a], ja.shape).any()


def test_inside_test_detects_overlap():
    """The interpenetration check itself: a point at a lattice's centre is inside, one beyond it is not."""
    from softsim_warp.core.lattice import lattice_points

    q = lattice_points((3, 3, 3), (1.0, 1.0, 1.0))
    assert _inside(np.array([[0.1, 0.05, -0.2], [0.6, 0.0, 0.0]]), q, (3, 3, 3)).tolist() == [True, False]


@pytest.mark.parametrize("turn", [0.0, 30.0])
def test_stack_stays_stacked(turn):
    """Three jellies on a plane (the top one also turned by 30 degrees about the vertical): no
    particle inside another jelly at any written frame, and the top one holds its height over the
    last 2 s: its centre moves less than 2 mm (2 % of the lattice spacing; the stack's slow elastic
    modes), does not sink (the mean of the last 0.5 s within 0.5 mm of that of 2.0-2.5 s), and it
    rests one pair distance above the middle one.

    No jitter: the drops leave the stack swaying at about 2 Hz (the top jelly's centre a few mm
    sideways), a mode that only the springs' damping takes down, and contact must not feed it. The
    top jelly's largest kinetic energy in each of the last three seconds is below 0.75 of that in
    the second before (0.005, 0.54 and 0.70 are measured, 0.003, 0.31 and 0.42 with the turn)."""
    scene = ss.load_scene("stack", [f"jelly.2.rotation={{axis=[0,1,0],degrees={turn}}}"])
    model, frames = _frames(scene)
    _no_interpenetration(model, frames)
    a, b, c = _jelly_slices(model)
    m = model.particle_mass_host[c]
    per_second = int(scene.sim["fps"])
    peaks = [
        max(0.5 * (m * (v[c] ** 2).sum(axis=1)).sum() for _, v in frames[k * per_second : (k + 1) * per_second])
        for k in range(len(frames) // per_second)
    ]
    for before, after in zip(peaks[-4:], peaks[-3:]):
        assert after < 0.75 * before
    late = [q for q, _ in frames[len(frames) // 2 :]]
    top = np.array([q[c, 1].mean() for q in late])
    assert np.ptp(top) < 2e-3
    quarter = len(top) // 4
    assert abs(top[-quarter:].mean() - top[:quarter].mean()) < 5e-4
    spacing = 0.1
    for q in late:
        # Resting on the middle jelly about one pair distance (one spacing) above its highest
        # particle (the faces bulge a little where they press).
        assert 0.85 * spacing < q[c, 1].min() - q[b, 1].max() < 1.1 * spacing


def test_pile_no_interpenetration():
    """The ten jellies of ``pile`` poured into the bowl: at none of its 601 written frames is any
    particle inside another jelly, and they come to rest in the bowl (the last one lands at 2 s): at
    its end (10 s) every particle is below 3 m, and their kinetic
    energy is below 1 J (2e-4 J is measured, against the 2.8e5 J of potential energy above y = 0 they
    start with)."""
    scene = ss.load_scene("pile")
    model, frames = _frames(scene)
    assert len(frames) == 601
    _no_interpenetration(model, frames)
    q, v = frames[-1]
    assert q[:, 1].max() < 3.0  # all of them came down into the heap
    assert 0.5 * (model.particle_mass_host * (v**2).sum(axis=1)).sum() < 1.0


def test_contact_keeps_the_springs_stable_step():
    """The response adds no stiffness, so a scene keeps its springs' own stable step: ``stack`` runs
    with contact at 0.99 of the largest stable symplectic step of its jellies' springs (linearised at
    rest, core/stability_analysis.py) and settles stacked, while at 1.1 of it the same jellies blow up
    with contact or without (the limit is the springs', not the contact's)."""
    from softsim_warp.core.stability_analysis import predict_lattice_dt

    scene = ss.load_scene("stack")
    jelly = scene.data["jelly"][0]  # the three jellies are alike
    springs = [jelly["springs"][t] for t in ("structural", "shear", "bending")]
    limit = predict_lattice_dt(
        tuple(jelly["resolution"]), jelly["size"], jelly["particle_mass"],
        [s["ks"] for s in springs], [s["kd"] for s in springs], methods=("symplectic",),
    )["symplectic"]
    assert scene.sim["dt"] <= limit < 1.1 * scene.sim["dt"]  # the scene itself runs at 0.93 of it

    def run(dt, overrides, seconds):
        scene = ss.load_scene("stack", overrides + [f"simulation.dt={dt!r}"])
        model = ss.build_model(scene, device="cpu")
        stepper = ss.Stepper(model, ss.make_integrator("symplectic", model), dt)
        stepper.advance(int(seconds / dt))
        return model, stepper.state.particle_q.numpy(), stepper.state.particle_qd.numpy()

    model, q, v = run(0.99 * limit, [], 2.0)
    assert np.isfinite(v).all() and np.linalg.norm(v, axis=1).max() < 0.2  # 0.06 m/s is measured
    a, b, c = _jelly_slices(model)
    assert q[a, 1].max() < q[b, 1].min() and q[b, 1].max() < q[c, 1].min()  # still stacked
    for overrides in ([], ["simulation.jelly_contact=false"]):
        assert not np.isfinite(run(1.1 * limit, overrides, 0.25)[2]).all()


# -- self-contact ---------------------------------------------------------------------------------


def _fold_min_distance(overrides):
    """The closest approach of the folding jelly's two halves over every written frame of ``fold``,
    and whether they swapped sides."""
    scene = ss.load_scene("fold", overrides)
    model, frames = _frames(scene)
    info = model.jellies[0]
    nx, ny, nz = info.shape
    i = np.arange(info.particle_count) // (ny * nz)
    left, right = i < nx // 2 - 3, i > nx // 2 + 3  # halves, at least 7 spacings apart at rest
    closest, crossed = np.inf, False
    for q, _ in frames:
        d = np.linalg.norm(q[left][:, None] - q[right][None], axis=2).min()
        closest = min(closest, d)
        crossed |= q[left, 0].mean() > q[right, 0].mean()
    return closest, crossed


def test_fold_self_contact_prevents_passing_through():
    """The halves of the folding jelly meet below the sphere: with self_contact they never come
    closer than 0.9 of the pair distance (0.1 m, one spacing); without it they pass through each
    other (the same scene, only the key changed)."""
    d = 0.1
    closest, crossed = _fold_min_distance([])
    assert closest >= 0.9 * d and not crossed
    closest, crossed = _fold_min_distance(["jelly.0.self_contact=false"])
    assert closest < 0.2 * d and crossed


def test_self_contact_excludes_rest_neighbours(monkeypatch):
    """Same-jelly pairs closer than SELF_EXCLUSION pair distances at rest never touch: a jelly that
    lands (squashed by the impact) and comes to rest on the ground with self_contact moves bit for
    bit as without it. Control: with the exclusion at one pair distance, the same jelly's
    neighbours touch each other where the landing squashes it, and it moves differently."""
    base = ["jelly.0.resolution=4"]
    frames = 120  # 2 s: it lands at about 0.35 s

    def final(overrides):
        return _frames(ss.load_scene("jelly_drop", base + overrides), frames=frames, every=frames)[1][-1][0]

    q_off = final([])
    q_on = final(["jelly.0.self_contact=true"])
    assert np.array_equal(q_on, q_off)
    assert q_on[:, 1].min() < 0.05  # it came down onto the ground
    monkeypatch.setattr(particle_contact, "SELF_EXCLUSION", 1.0)
    q_near = final(["jelly.0.self_contact=true"])
    assert not np.array_equal(q_near, q_off)


# -- friction ----------------------------------------------------------------------------------------


def _slope(theta_deg, mu, integrator="symplectic"):
    """A 4^3 block on a 31x3x6 jelly slab lying on a plane that holds it (friction 10); gravity
    tilted by theta instead of the slab. Returns the block's displacement along the slope relative
    to the slab over 1.5 s, its acceleration fitted over the last second, the acceleration Coulomb's
    law gives for sliding, and its displacement over the last 0.5 s."""
    g, t = 9.8, math.radians(theta_deg)

    def springs(ks, kd):
        return {"structural": {"ks": ks, "kd": kd}, "shear": {"ks": ks, "kd": kd}, "bending": {"ks": ks / 2, "kd": kd / 2}}

    data = {
        "simulation": {
            "dt": 5e-4,
            "duration": 1.5,
            "gravity": [g * math.sin(t), -g * math.cos(t), 0.0],
            "jelly_contact_friction": mu,
        },
        "jelly": [
            {"resolution": [31, 3, 6], "size": [3.0, 0.2, 0.5], "center": [0.0, 0.1, 0.0], "total_mass": 8.0,
             "springs": springs(2000.0, 2.0)},
            {"resolution": [4, 4, 4], "size": 0.3, "center": [-1.0, 0.455, 0.0], "total_mass": 1.0,
             "springs": springs(500.0, 1.0)},
        ],
        "plane": [{"point": [0, 0, 0], "normal": [0, 1, 0], "friction": 10.0, "restitution": 0.0}],
    }
    scene = ss.scene_from_dict(data)
    model = ss.build_model(scene, device="cpu")
    stepper = ss.Stepper(model, ss.make_integrator(integrator, model), scene.sim["dt"])
    slab, block = _jelly_slices(model)
    xs, ts = [], []
    for k in range(31):
        if k:
            stepper.advance(100)
        q = stepper.state.particle_q.numpy()
        xs.append(q[block, 0].mean() - q[slab, 0].mean())
        ts.append(k * 100 * scene.sim["dt"])
    xs, ts = np.array(xs), np.array(ts)
    late = ts >= 0.5
    accel = 2.0 * np.polyfit(ts[late], xs[late], 2)[0]
    return xs[-1] - xs[0], accel, g * (math.sin(t) - mu * math.cos(t)), xs[-1] - xs[ts >= 1.0][0]


@pytest.mark.parametrize("theta, mu", [(15.0, 0.5), (25.0, 0.5), (10.0, 0.2)])
def test_block_sticks_below_friction_angle(theta, mu):
    """tan(theta) < mu: the block settles onto the slab, the two soft jellies shearing under the load
    along the slope (less than half the block's lattice spacing of 0.1 m: 0.4, 2.9 and 0.8 cm are
    measured), and then stays: less than 1 mm over the last 0.5 s (a block sliding at 30 degrees
    moves 46 cm in it) and no acceleration."""
    assert math.tan(math.radians(theta)) < mu
    moved, accel, _, late = _slope(theta, mu)
    assert abs(moved) < 0.05 and abs(late) < 1e-3 and abs(accel) < 0.01


@pytest.mark.parametrize(
    "theta, mu, integrator",
    [
        (35.0, 0.5, "symplectic"),
        (20.0, 0.2, "symplectic"),
        (35.0, 0.5, "midpoint"),
        (35.0, 0.5, "rk4"),
        (35.0, 0.5, "implicit"),
    ],
)
def test_block_slides_with_coulomb_acceleration(theta, mu, integrator):
    """tan(theta) > mu: the block slides with a = g (sin(theta) - mu cos(theta)), within 0.5 % (0.05 to
    0.2 % is measured)."""
    moved, accel, expected, _ = _slope(theta, mu, integrator)
    assert moved > 0.5
    assert accel == pytest.approx(expected, rel=0.005)


# -- worlds, determinism --------------------------------------------------------------------------------


def test_worlds_never_touch():
    """Two copies of collide in two worlds, on top of each other: each world moves as collide alone."""
    scene = ss.load_scene("collide", SMALL_COLLIDE + ["simulation.precision=float64"])
    builder = ModelBuilder(scene.sim["gravity"])
    populate(builder, scene.data, world=0)
    populate(builder, scene.data, world=1)
    batched = builder.finalize("cpu", "float64")
    _, both = _frames(scene, model=batched, frames=30, every=30)
    _, alone = _frames(scene, frames=30, every=30)
    n = alone[-1][0].shape[0]
    for w in range(2):
        assert np.abs(both[-1][0][w * n : (w + 1) * n] - alone[-1][0]).max() < 1e-9


def test_cpu_bitwise_reproducible():
    scene = ss.load_scene("collide", SMALL_COLLIDE)
    first = _frames(scene, frames=30, every=30)[1][-1]
    second = _frames(scene, frames=30, every=30)[1][-1]
    assert np.array_equal(first[0], second[0]) and np.array_equal(first[1], second[1])


def test_deterministic_on_every_device(device):
    """The response sums each particle's contacts in ascending partner order: no atomics, so
    --deterministic runs are bitwise identical on CUDA as on the CPU."""
    scene = ss.load_scene("collide", SMALL_COLLIDE)
    runs = []
    for _ in range(2):
        model = ss.build_model(scene, device=device, deterministic=True, force_path="springs")
        runs.append(_frames(scene, model=model, frames=20, every=20)[1][-1])
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])
    assert wp.get_device(device) is not None


# -- the benchmark ----------------------------------------------------------------------------------


def test_bench_contact_cli(tmp_path, capsys):
    """``softsim bench --contact`` on tiny piles: a row with and without contact per count, on the
    same particles, the block of jellies touching from the first step, and a bad count refused."""
    from softsim_warp.studies import bench_contact
    from softsim_warp.studies.bench import JellySpec
    from softsim_warp.commands.cli import main

    out = tmp_path / "contact.json"
    argv = ["bench", "--contact", "--jellies", "2,8", "--contact-size", "3", "--steps", "4", "--repeats", "1"]
    assert main(argv + ["--out", str(out)]) == 0
    rows = __import__("json").loads(out.read_text())["results"]
    assert [(r["jellies"], r["contact"]) for r in rows] == [(2, False), (2, True), (8, False), (8, True)]
    assert all(r["finite"] for r in rows) and rows[1]["particles"] == rows[0]["particles"] == 54
    assert rows[0]["contact_cost"] == 1.0
    assert "x no-contact" in capsys.readouterr().out
    # Neighbouring jellies start 0.85 spacings apart: inside the pair distance of one spacing.
    spec = JellySpec()
    model = bench_contact.build_pile(8, 3, spec, "cpu")
    hook = model.run_state().particle_contact
    hook(model, model.state(), model.state(), model.scalar(spec.dt), wp.ones(1, dtype=model.scalar, device="cpu"))
    assert hook.contacts.numpy().sum() > 0
    assert main(["bench", "--contact", "--jellies", "1"]) == 2

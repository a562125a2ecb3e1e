"""Candidate lists of contact between jellies (kernels/particle_contact/, core/particle_contact.py).

A list holds the pairs within CANDIDATE_REACH d + skin at its build and is rebuilt once a particle
has moved half the skin. Checked against what cannot agree by accident: a brute-force O(n^2) NumPy
search in float64 (every allowed pair, by world, jelly, self-exclusion and distance), a hook that
builds fresh lists on the same positions (the contacts, normals and gaps must be bitwise the same),
and the lists' overflow paths (tiny lists), which must give bitwise the same step.
"""

import numpy as np
import pytest
import warp as wp

import softsim_warp as ss
from softsim_warp.core import particle_contact
from softsim_warp.core.model import ModelBuilder

SPACING = 0.05
SIZE = 4


def _pile(self_contact=False, worlds=1, precision="float32", iterations=None):
    """Eight jellies of 4^3 in a 2x2x2 block, 0.85 spacings apart (every face touches), in
    ``worlds`` copies on top of each other."""
    builder = ModelBuilder((0.0, -9.81, 0.0))
    springs = {t: {"ks": 1000.0, "kd": 0.0} for t in ("structural", "shear", "bending")}
    edge = SPACING * (SIZE - 1)
    pitch = edge + 0.85 * SPACING
    for world in range(worlds):
        for c in range(8):
            centre = ((c % 2) * pitch, (c // 2 % 2) * pitch + 0.5, (c // 4) * pitch)
            builder.add_jelly(
                (SIZE,) * 3, edge, 0.01, springs, center=centre, world=world, self_contact=self_contact and c == 0
            )
    builder.jelly_contact = True
    if iterations is not None:
        builder.jelly_contact_iterations = iterations
    return builder.finalize("cpu", precision)


def _step_hook(hook, model, state, q):
    """One call of ``hook`` (a run's ParticleContactState) on positions ``q`` (the step's result) and
    zero velocities; returns the state."""
    state.particle_q.assign(q.astype(np.float32))
    state.particle_qd.zero_()
    hook(model, state, state, model.scalar(1e-4), wp.ones(4, dtype=model.scalar, device="cpu"))
    return state


def _brute_force(hook, x, reach_extra):
    """Every contact particle's allowed partners within CANDIDATE_REACH d + ``reach_extra`` of it at
    contact positions ``x`` (float64), by checking all pairs."""
    jelly = hook.contact_jelly.numpy()
    world = hook.contact_world.numpy()
    radius = hook.contact_radius.numpy().astype(np.float64)
    self_flag = hook.jelly_self_contact.numpy()
    rest = hook.contact_rest.numpy().astype(np.float64)
    d = radius[:, None] + radius[None, :]
    dist = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=2)
    same = jelly[:, None] == jelly[None, :]
    allowed = (world[:, None] == world[None, :]) & ~np.eye(len(x), dtype=bool)
    if rest.shape[0] == len(x):
        rest_dist = np.linalg.norm(rest[:, None, :] - rest[None, :, :], axis=2)
        self_ok = (self_flag[jelly][:, None] == 1) & (rest_dist >= particle_contact.SELF_EXCLUSION * d)
    else:
        self_ok = np.zeros_like(same)
    allowed &= np.where(same, self_ok, hook.between_jellies == 1)
    near = dist < 1.25 * d + reach_extra
    return [set(np.flatnonzero(row)) for row in (allowed & near)]


def _lists(hook):
    cand = hook.candidates.numpy()
    count = hook.candidate_count.numpy()
    return [list(cand[: count[i], i]) for i in range(hook.count)]


def _contacts(hook):
    c = hook.contacts.numpy()
    lst, nrm, gap = hook.contact_list.numpy(), hook.contact_normal.numpy(), hook.contact_gap.numpy()
    return [(list(lst[: c[i], i]), nrm[: c[i], i].tolist(), gap[: c[i], i].tolist()) for i in range(hook.count)]


@pytest.mark.parametrize("self_contact", [False, True])
def test_candidate_lists_match_brute_force(self_contact):
    """After a build, each list is exactly the brute-force set of allowed partners within
    CANDIDATE_REACH d + skin, in ascending order (so the sums do not depend on the grid)."""
    model = _pile(self_contact)
    hook = model.run_state().particle_contact
    rng = np.random.default_rng(1)
    # Jitter by up to 0.4 spacings: pairs across the reach, and with self-contact, pairs of one
    # jelly far apart in the rest shape that come close.
    q = model.particle_q_host + rng.uniform(-0.4, 0.4, model.particle_q_host.shape) * SPACING
    _step_hook(hook, model, model.state(), q)
    assert hook.builds_done() == 1
    x = q[hook.contact_index.numpy()].astype(np.float32).astype(np.float64)
    expected = _brute_force(hook, x, hook.skin_host)
    lists = _lists(hook)
    assert all(lst == sorted(lst) for lst in lists)
    assert [set(lst) for lst in lists] == expected
    assert sum(len(e) for e in expected) > hook.count  # the scene has pairs to find
    if self_contact:
        jelly = hook.contact_jelly.numpy()
        assert any(jelly[i] == jelly[j] for i, e in enumerate(expected) for j in e)


def test_lists_kept_give_the_contacts_of_a_fresh_build():
    """Particles moved by just under the rebuild distance: the lists are not rebuilt, every pair
    within CANDIDATE_REACH d now is in them, and the contacts (partners, normals, gaps) are bitwise
    those of a hook that builds its lists on the moved positions."""
    model = _pile()
    hook = model.run_state().particle_contact
    rng = np.random.default_rng(2)
    q0 = model.particle_q_host + rng.uniform(-0.2, 0.2, model.particle_q_host.shape) * SPACING
    _step_hook(hook, model, model.state(), q0)
    # Each particle moves by 0.99 of the rebuild distance in a random direction.
    step = rng.normal(size=q0.shape)
    step *= 0.99 * float(hook.rebuild_distance) / np.linalg.norm(step, axis=1, keepdims=True)
    q1 = q0 + step
    _step_hook(hook, model, model.state(), q1)
    assert hook.builds_done() == 1
    x1 = q1[hook.contact_index.numpy()].astype(np.float32).astype(np.float64)
    within_reach = _brute_force(hook, x1, 0.0)
    assert all(e <= set(lst) for e, lst in zip(within_reach, _lists(hook)))
    fresh = _pile()
    fresh_hook = fresh.run_state().particle_contact
    _step_hook(fresh_hook, fresh, fresh.state(), q1)
    assert fresh_hook.builds_done() == 1
    assert _contacts(hook) == _contacts(fresh_hook)
    assert hook.contacts.numpy().sum() > 0


def test_rebuild_when_a_particle_moves_half_the_skin():
    """One particle moved by more than the rebuild distance (just under skin / 2) rebuilds the lists;
    moves below it do not."""
    model = _pile()
    hook = model.run_state().particle_contact
    assert hook.rebuild_distance < 0.5 * hook.skin_host < 1.05 * hook.rebuild_distance
    q = model.particle_q_host.copy()
    _step_hook(hook, model, model.state(), q)
    p = int(hook.contact_index.numpy()[5])
    for moved, builds in ((0.9, 1), (0.98, 1), (1.02, 2)):
        q1 = q.copy()
        q1[p, 1] += moved * float(hook.rebuild_distance)
        _step_hook(hook, model, model.state(), q1)
        assert hook.builds_done() == builds, moved
    # The build of the last call measures moves from there.
    _step_hook(hook, model, model.state(), q1)
    assert hook.builds_done() == 2


def test_worlds_get_no_candidates_of_each_other():
    model = _pile(worlds=2)
    hook = model.run_state().particle_contact
    _step_hook(hook, model, model.state(), model.particle_q_host)
    world = hook.contact_world.numpy()
    assert all(world[j] == world[i] for i, lst in enumerate(_lists(hook)) for j in lst)
    assert sum(len(lst) for lst in _lists(hook)) > 0


def _squeezed_pile(steps, precision="float32", iterations=None):
    """``steps`` symplectic steps of the pile squeezed along x (particles with several contacts);
    returns the positions, the velocities, the model and the integrator's contact state."""
    from softsim_warp.core.stepper import make_integrator

    model = _pile(precision=precision, iterations=iterations)
    q = model.particle_q_host.copy()
    q[:, 0] *= 0.97
    state = [model.state(), model.state()]
    state[0].particle_q.assign(q.astype(model.particle_q_host.dtype))
    integrator = make_integrator("symplectic", model)
    for k in range(steps):
        integrator.step(state[k % 2], state[1 - k % 2], 1e-4)
    return (state[steps % 2].particle_q.numpy(), state[steps % 2].particle_qd.numpy(), model,
            integrator.run.particle_contact)


def test_full_candidate_lists_step_bitwise_the_same(monkeypatch):
    """With candidate lists of 2 (the grid walk takes over), ten steps of a squeezed pile are bitwise
    those with the full lists."""
    q_full, v_full, _, hook = _squeezed_pile(10)
    most = hook.candidate_count.numpy().max()
    monkeypatch.setattr(particle_contact, "MAX_CANDIDATES", 2)
    q_short, v_short, _, short = _squeezed_pile(10)
    assert most > 2 and (short.candidate_count.numpy() == 3).any()  # they do overflow
    assert np.array_equal(q_full, q_short) and np.array_equal(v_full, v_short)


def test_accumulated_impulses_are_equal_and_opposite():
    """After ten steps of the squeezed pile (four passes, warm started from the step before), every
    pair that both lists hold has stored impulses that are exact negatives of each other, and its
    partners' normals too: each particle computes the pair's impulse from the pair's values alone."""
    _, _, _, hook = _squeezed_pile(10, iterations=4)
    half = int(hook.phase.numpy()[0])
    slots = particle_contact.MAX_CONTACTS
    count = hook.contacts.numpy()
    partner = hook.contact_list.numpy()
    impulse = hook.contact_impulse.numpy()[half * slots : (half + 1) * slots]
    normal = hook.contact_normal.numpy()
    pairs = 0
    for i in np.flatnonzero((count > 0) & (count <= slots)):
        for a in range(count[i]):
            j = partner[a, i]
            if count[j] > slots:
                continue
            b = list(partner[: count[j], j]).index(i)  # the lists are symmetric
            assert np.array_equal(impulse[a, i], -impulse[b, j]) and np.array_equal(normal[a, i], -normal[b, j])
            pairs += 1
    assert pairs > 100 and np.abs(impulse).max() > 0


def test_overflowed_contact_lists_conserve_momentum(monkeypatch):
    """With contact lists of 1, a particle with more contacts tests its candidates again in each pass,
    and its pairs take impulses that do not accumulate (both particles of a pair decide that alike,
    from whether both lists hold it), beside pairs that do. Ten steps of the squeezed pile in float64
    with three passes (in a first pass without a warm start the two kinds of impulse agree): the
    contacts push the jellies apart, and the total momentum is the gravity's to rounding."""
    monkeypatch.setattr(particle_contact, "MAX_CONTACTS", 1)
    q, v, model, hook = _squeezed_pile(10, "float64", iterations=3)
    counts = hook.contacts.numpy()
    assert (counts > 1).any() and (counts == 1).any()  # overflowed lists beside full ones
    mass = 1.0 / model.particle_inv_mass.numpy()
    expected = mass.sum() * np.array([0.0, -9.81 * 10 * 1e-4, 0.0])
    momentum = (mass[:, None] * v).sum(axis=0)
    spread = np.abs(mass[:, None] * v).sum()
    assert np.abs(v[:, 0]).max() > 1e-3  # the contacts act (gravity is along y)
    assert np.abs(momentum - expected).max() <= 1e-12 * spread, (momentum, expected)


def test_face_order_groups_each_face():
    """The contact particles are every jelly's surface particles, numbered face by face: all
    particles on one boundary face first (each face's together, in lattice order), then those on
    two (each edge's together), then the corners; so a warp's threads share a face."""
    model = _pile()
    hook = model.run_state().particle_contact
    index = hook.contact_index.numpy()
    per_jelly = SIZE**3 - (SIZE - 2) ** 3
    assert hook.count == 8 * per_jelly
    expected = set()
    for j in model.jellies:
        local = np.flatnonzero(particle_contact.surface_mask(j.shape))
        expected |= set((local + j.particle_start).tolist())
    assert sorted(index.tolist()) == sorted(expected)
    # Each particle's boundary faces, from its lattice coordinates.
    start = np.array([j.particle_start for j in model.jellies])
    jelly = np.searchsorted(start, index, side="right") - 1
    ijk = np.stack(np.unravel_index(index - start[jelly], (SIZE,) * 3), axis=1)
    sides = np.concatenate([ijk == 0, ijk == SIZE - 1], axis=1)
    faces = sides.sum(axis=1)
    assert np.all(np.diff(faces) >= 0)
    face = SIZE - 2  # particles on one face of a 4^3 jelly: a 2x2 patch each
    assert np.count_nonzero(faces == 1) == 8 * 6 * face**2
    # Within the particles of one face count, one group per (jelly, set of faces), each contiguous
    # and in ascending particle order.
    key = jelly * 64 + (sides * (1 << np.arange(6))).sum(axis=1)
    runs = np.flatnonzero(np.diff(key) != 0) + 1
    groups = np.split(np.arange(index.size), runs)
    assert len(groups) == len(set(key.tolist())) == 8 * 26
    for g in groups:
        assert np.all(np.diff(index[g]) > 0)


def test_capacity_is_a_user_error(monkeypatch):
    """The kernels address the contact tables with 32-bit element offsets. The largest offset they
    compute (3 (slots n - 1) in the widest table, the contacts' impulses of a built hook: this step's
    and the last) fits at the limit and not one contact particle beyond it, and a model beyond the
    limit is refused by build_model with a one-line scene error."""
    from softsim_warp.core.errors import SceneError

    hook = ss.build_model(ss.load_scene("collide", ["jelly.0.resolution=3", "jelly.1.resolution=3"])).run_state().particle_contact
    slots = hook.contact_impulse.shape[0]
    assert all(a.shape[0] <= slots for a in (hook.contact_normal, hook.contact_lists, hook.candidates))
    limit = particle_contact.MAX_CONTACT_PARTICLES
    assert 3 * (slots * limit - 1) <= 2**31 - 1 < 3 * (slots * (limit + 1) - 1)
    assert hook.candidates.shape[0] * limit - 1 <= 2**31 - 1
    assert 3 * (particle_contact.MAX_PARTICLES - 1) <= 2**31 - 1 < 3 * particle_contact.MAX_PARTICLES
    monkeypatch.setattr(particle_contact, "MAX_CONTACT_PARTICLES", hook.count - 1)
    with pytest.raises(SceneError) as err:
        ss.build_model(ss.load_scene("collide", ["jelly.0.resolution=3", "jelly.1.resolution=3"]))
    line = str(err.value)
    assert "\n" not in line and line.startswith("scene: simulation.jelly_contact: ")
    assert f"(got [{hook.count}, {2 * 27}])" in line


def test_strided_state_is_refused():
    """The contact kernels address the particle state from its data pointer: a strided view is refused."""
    model = ss.build_model(ss.load_scene("collide", ["jelly.0.resolution=3", "jelly.1.resolution=3"]))
    wide = wp.zeros(2 * model.particle_count, dtype=model.vec3, device=model.device)
    state_in, state_out = model.state(), model.state()
    state_out.particle_q = wide[::2]
    with pytest.raises(ValueError, match="jelly contact kernels need contiguous"):
        model.run_state().particle_contact(model, state_in, state_out, 1.0e-3, wp.ones(1, dtype=model.scalar))


def test_warm_up_and_restart_leave_no_contact_history():
    """The impulses a step keeps for the next one's warm start are forgotten by a new stepper, after
    the warm-up step and on a restart: a run after either is bitwise the run without it (the pile
    touches from its first step, so a kept impulse would start the first step warm, and does)."""
    from softsim_warp.core.stepper import Stepper, make_integrator

    def stepper(model, warm_up=False):
        s = Stepper(model, make_integrator("symplectic", model), 1e-4, use_graph=False)
        if warm_up:
            s.warm_up()
        return s

    def result(s):
        s.advance(5)
        return s.state.particle_q.numpy(), s.state.particle_qd.numpy()

    def restart(s, model, forget):  # the stepper's own run state forgets, the model holds none
        wp.copy(s.states[0].particle_q, model.particle_q)
        wp.copy(s.states[0].particle_qd, model.particle_qd)
        s.current = 0
        if forget:
            s.integrator.run.forget_contact_history()

    q, v = result(stepper(_pile()))
    model = _pile()
    result(stepper(model))
    for s in (stepper(model), stepper(_pile(), warm_up=True)):
        assert np.array_equal((q, v), result(s))
    s = stepper(model)
    result(s)
    restart(s, model, forget=True)
    assert np.array_equal((q, v), result(s))
    restart(s, model, forget=False)
    assert not np.array_equal(q, result(s)[0])


@pytest.mark.parametrize("iterations", [1, 2])
def test_a_pair_with_an_overflowed_list_does_not_accumulate(monkeypatch, iterations):
    """Three one-particle jellies, contact lists of one. In the first step A and B touch, alone, and
    their impulse accumulates; in the next, C touches B too (B's list overflows) while A and B move
    apart. Both start the pair from the last step's impulse, and then neither takes it back (which
    an accumulating A alone would do); in a third, neither starts it warm (B's list did not hold the
    pair in the second). Momentum holds to rounding in float64 in each step, with one velocity pass
    (the default) and with two (where the first pass's rule could hide the last one's)."""
    monkeypatch.setattr(particle_contact, "MAX_CONTACTS", 1)
    builder = ModelBuilder((0.0, 0.0, 0.0))
    springs = {t: {"ks": 1000.0, "kd": 0.0} for t in ("structural", "shear", "bending")}
    for mass, centre in ((0.01, (-0.045, 0.0, 0.0)), (0.02, (0.0, 0.0, 0.0)), (0.01, (0.01, 1.0, 0.0))):
        builder.add_jelly((1, 1, 1), 0.0, mass, springs, center=centre)
    builder.jelly_contact = True
    builder.jelly_contact_thickness = 0.05
    builder.jelly_contact_iterations = iterations
    model = builder.finalize("cpu", "float64")
    hook = model.run_state().particle_contact
    mass = np.array([0.01, 0.02, 0.01])

    def step(q, v):
        state = model.state()
        state.particle_q.assign(np.asarray(q, dtype=np.float64))
        state.particle_qd.assign(np.asarray(v, dtype=np.float64))
        hook(model, state, state, model.scalar(1e-4), wp.ones(1, dtype=model.scalar, device="cpu"))
        return state.particle_qd.numpy(), hook.contacts.numpy()

    q = [[-0.045, 0.0, 0.0], [0.0, 0.0, 0.0], [0.01, 1.0, 0.0]]
    v1, count = step(q, [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert list(count) == [1, 1, 0] and v1[0, 0] < 0.1  # A and B pushed apart
    q[2] = [0.01, 0.045, 0.0]
    v = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, -0.1, 0.0]])
    v2, count = step(q, v)
    assert list(count) == [1, 2, 1]
    assert np.abs((mass[:, None] * (v2 - v)).sum(axis=0)).max() < 1e-15
    # A third step: A's list still holds the pair's warm start of the second, but B's overflowed then,
    # so neither starts the pair warm.
    v = np.array([[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0], [0.0, -0.1, 0.0]])
    v3, count = step(q, v)
    assert list(count) == [1, 2, 1]
    assert np.abs((mass[:, None] * (v3 - v)).sum(axis=0)).max() < 1e-15

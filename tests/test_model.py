"""The Model is declared and frozen; what a run writes is each integrator's own (core/model.py RunState).

Two steppers on one model, each with its own integrator, stepped in turn, give bitwise what each
gives alone on the CPU, in scenes whose steps write every kind of run state: driven pins (their
clock), moving terrain (its clock and poses), contact between jellies and self-contact (candidate
lists, the warm start's impulses) and the CPU lattice row kernel's scratch.
"""

import numpy as np
import pytest

import softsim_warp as ss
from softsim_warp.core.model import Model, ModelBuilder

SPRINGS = {"structural": {"ks": 400.0, "kd": 0.5}, "shear": {"ks": 400.0, "kd": 0.5}, "bending": {"ks": 100.0, "kd": 0.2}}


def _everything_scene():
    """Two small jellies stacked on a plane that slides and spins; the top one is driven down into
    the lower one by a pin on its top face, and the bottom one is pushed around by the plane."""
    return ss.scene_from_dict({
        "simulation": {"integrator": "symplectic", "dt": 1e-3, "duration": 1.0},
        "jelly": [
            {"resolution": 3, "size": 0.2, "center": [0.0, 0.101, 0.0], "particle_mass": 0.01, "springs": SPRINGS},
            {"resolution": 3, "size": 0.2, "center": [0.0, 0.31, 0.0], "particle_mass": 0.01, "springs": SPRINGS},
        ],
        "plane": [{"friction": 0.8, "restitution": 0.0,
                   "motion": {"velocity": [0.3, 0.0, 0.0], "spin": {"axis": [0.0, 1.0, 0.0], "degrees_per_second": 90.0}}}],
        "sphere": [{"center": [0.6, 0.0, 0.0], "radius": 0.15, "motion": {"velocity": [-0.5, 0.0, 0.0]}}],
        "pin": [{"jelly": 1, "face": "+y", "velocity": [0.0, -0.2, 0.0]}],
    })


SCENES = {
    "pins_terrain_contact": _everything_scene,
    "twist": lambda: ss.load_scene("twist", ["jelly.0.resolution=[12, 4, 4]", "simulation.dt=1e-3"]),
    "platform": lambda: ss.load_scene("platform", ["jelly.0.resolution=3", "jelly.1.resolution=3",
                                                   "jelly.2.resolution=3"]),
}
# Steps taken per call, in turn: odd counts leave either state buffer current, so both graph keys
# of each count are captured and replayed.
CHUNKS = [7, 13, 1, 20, 9, 50]


def _advance(stepper, k):
    stepper.advance(CHUNKS[k % len(CHUNKS)])


def _result(stepper):
    return stepper.state.particle_q.numpy().copy(), stepper.state.particle_qd.numpy().copy()


@pytest.mark.parametrize("name", list(SCENES))
def test_two_steppers_on_one_model_run_independently(name):
    scene = SCENES[name]()
    methods = ("symplectic", "midpoint")
    rounds = 12

    def stepper(model, method):
        return ss.Stepper(model, ss.make_integrator(method, model), scene.sim["dt"])

    alone = []
    for method in methods:
        model = ss.build_model(scene, device="cpu")
        s = stepper(model, method)
        for k in range(rounds):
            _advance(s, k)
        alone.append(_result(s))

    model = ss.build_model(scene, device="cpu")
    plane_point = model.plane_point.numpy().copy()
    steppers = [stepper(model, method) for method in methods]
    for k in range(rounds):
        for s in steppers:
            _advance(s, k)
    for s, (q, qd) in zip(steppers, alone, strict=True):
        got_q, got_qd = _result(s)
        assert np.array_equal(got_q, q) and np.array_equal(got_qd, qd)
    # The scene did write what it should: the runs differ (two methods), contact happened where
    # the scene has it, moving terrain moved in each run's poses and not in the model's arrays.
    assert not np.array_equal(alone[0][0], alone[1][0])
    run = steppers[0].integrator.run
    assert run is not steppers[1].integrator.run
    if model.particle_contact is not None:
        assert run.particle_contact.builds_done() >= 1
    if name == "pins_terrain_contact":  # the jellies touch (the pin drives one into the other)
        assert run.particle_contact.contacts.numpy().any()
    if model.terrain_motion is not None and model.plane_count:
        np.testing.assert_array_equal(model.plane_point.numpy(), plane_point)
        moved = [m for m, it in zip(run.terrain.plane_point.numpy(), model.planes) if it["motion"] is not None]
        still = [m for m, it in zip(plane_point, model.planes) if it["motion"] is not None]
        if name != "platform":  # (the platform's keys start at 0.875 s, after these steps)
            assert any(not np.array_equal(a, b) for a, b in zip(moved, still))
    if name == "pins_terrain_contact":
        assert model.pins is not None and run.pin_clock.numpy()[0] == sum(
            CHUNKS[k % len(CHUNKS)] for k in range(rounds))


def test_a_finalized_model_refuses_changes():
    model = ss.build_model(SCENES["pins_terrain_contact"](), device="cpu")
    with pytest.raises(AttributeError, match="frozen"):
        model.particle_qd = model.particle_q
    with pytest.raises(AttributeError, match="frozen"):
        model.contact_hooks = ()
    with pytest.raises(AttributeError, match="frozen"):
        model.something_new = 1
    with pytest.raises(AttributeError, match="frozen"):
        del model.pins
    assert model.pins is not None


def test_every_declared_field_is_present():
    """Each declared field is set on every model, None where the scene lacks the part; nothing else is."""
    for scene in (ss.load_scene("jelly_drop"), SCENES["pins_terrain_contact"]()):
        model = ss.build_model(scene, device="cpu")
        assert set(Model.fields()) <= set(vars(model))
        assert set(vars(model)) - set(Model.fields()) <= {"_frozen", "_derived", "_spring_blocks"}
    plain = ss.build_model(ss.load_scene("jelly_drop"), device="cpu")
    for name in ("pins", "terrain_motion", "plane_motion", "mesh_animation", "mesh_motion", "particle_contact",
                 "masked", "spring_csr_offsets"):
        assert getattr(plain, name) is None, name
    assert plain.contact_hooks == () and plain.mesh_count == 0 and plain.deterministic is False


def test_the_lazy_spring_list_is_made_once_through_the_cache():
    """On the lattice path the spring list is made on first access, the one change the freeze allows."""
    b = ModelBuilder()
    b.add_jelly((3, 3, 3), 0.2, 0.01, SPRINGS)
    model = b.finalize("cpu")
    assert model.lattice is not None and not model.has_derived("spring_indices")
    first = model.spring_indices
    assert model.has_derived("spring_indices")
    assert model.spring_indices is first and first.shape[0] == model.spring_count
    assert model.spring_indices_host.shape == (model.spring_count, 2)


def test_deterministic_csr_is_made_by_finalize():
    b = ModelBuilder()
    b.add_jelly((3, 2, 2), 0.2, 0.01, SPRINGS)
    model = b.finalize("cpu", force_path="springs", deterministic=True)
    assert model.deterministic and model.spring_csr_offsets.shape[0] == model.particle_count + 1
    assert model.run_state().forces.spring_force.shape[0] == model.spring_count

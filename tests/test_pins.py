"""Pins: held and driven particles against closed forms, on every integrator.

A held column under gravity sags to the static solution of a chain of springs; a driven pin follows
its path exactly (to rounding) whatever the integrator; pinned particles take no contact; the scene
keys are validated like every other key.
"""

import numpy as np
import pytest

import softsim_warp as ss
from softsim_warp.core.errors import SceneError
from softsim_warp.core.pins import path_position

METHODS = ["euler", "symplectic", "midpoint", "rk4", "implicit"]
SPRINGS = {"structural": {"ks": 50.0, "kd": 0.1}, "shear": {"ks": 50.0, "kd": 0.1}, "bending": {"ks": 25.0, "kd": 0.05}}


def column_scene(n, ks, kd, mass, spacing, integrator, duration):
    """A vertical column of n particles (structural springs only) held by its top particle."""
    return ss.scene_from_dict({
        "simulation": {"integrator": integrator, "dt": 1e-3, "duration": duration, "gravity": [0.0, -9.8, 0.0],
                       "precision": "float64"},
        "jelly": [{"resolution": [1, n, 1], "size": [1.0, spacing * (n - 1), 1.0], "center": [0.0, 0.0, 0.0],
                   "particle_mass": mass, "springs": {"structural": {"ks": ks, "kd": kd}}}],
        "pin": [{"face": "+y"}],
    })


@pytest.mark.parametrize("method", ["symplectic", "implicit"])
def test_held_column_sags_to_the_static_solution(method):
    """Spring i (from the top) carries the weight of the n - i particles below it, so it stretches
    by (n - i) m g / ks; the particles' heights are the running sums of rest length plus stretch."""
    n, ks, kd, mass, spacing = 6, 200.0, 10.0, 0.05, 0.1
    scene = column_scene(n, ks, kd, mass, spacing, method, 10.0)
    model = ss.build_model(scene, "cpu")
    stepper = ss.Stepper(model, ss.make_integrator(method, model), scene.sim["dt"])
    stepper.advance(10_000)
    y = np.sort(stepper.state.particle_q.numpy()[:, 1])[::-1]  # top first
    top = spacing * (n - 1) / 2
    stretch = np.array([(n - i) * mass * 9.8 / ks for i in range(1, n)])
    expected = top - np.concatenate([[0.0], np.cumsum(spacing + stretch)])
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-9)
    assert np.abs(stepper.state.particle_qd.numpy()).max() < 1e-8


@pytest.mark.parametrize("method", METHODS)
def test_driven_pin_follows_its_path_exactly(method):
    """Velocity, spin and smooth keyframes together: at every step the pinned particles are on the
    path to float64 rounding, while the free ones swing below them."""
    b = ss.ModelBuilder(gravity=(0.0, -9.8, 0.0))
    j = b.add_jelly((4, 4, 4), 0.3, 0.01, SPRINGS, center=(0.0, 1.0, 0.0))
    top = [j.particle_start + i for i in range(64) if (i // 4) % 4 == 3]
    pid = b.add_pin(top, velocity=(0.1, 0.0, 0.0), spin=(0.0, 1.0, 0.0), key_times=[0.0, 0.5, 1.0],
                    key_offsets=[[0, 0, 0], [0, 0.2, 0], [0, 0, 0]], interpolation="smooth")
    model = b.finalize("cpu", "float64")
    stepper = ss.Stepper(model, ss.make_integrator(method, model), 1e-3)
    pin = b.pins[pid]
    x0 = model.particle_q_host[pin["particles"]]
    done = 0
    for k in (1, 37, 250, 700):
        stepper.advance(k - done)
        done = k
        q = stepper.state.particle_q.numpy()
        np.testing.assert_allclose(q[pin["particles"]], path_position(pin, x0, k * 1e-3), rtol=0, atol=1e-12)
    free = np.setdiff1d(np.arange(model.particle_count), pin["particles"])
    assert np.isfinite(q).all() and q[free, 1].max() < q[pin["particles"], 1].min()


def test_path_interpolation_closed_forms():
    """Linear keys interpolate linearly; smooth keys pass through every key with the Catmull-Rom
    tangent (central difference) at inner keys; spin is a rotation about the moving centre."""
    pin = {"center": np.zeros(3), "velocity": np.zeros(3), "spin": np.zeros(3), "key_times": [0.0, 1.0, 3.0],
           "key_offsets": [[0, 0, 0], [1, 0, 0], [1, 2, 0]], "interpolation": "linear"}
    x0 = np.array([0.0, 0.0, 0.0])
    np.testing.assert_allclose(path_position(pin, x0, 0.5), [0.5, 0, 0])
    np.testing.assert_allclose(path_position(pin, x0, 2.0), [1, 1, 0])
    np.testing.assert_allclose(path_position(pin, x0, 9.0), [1, 2, 0])  # held after the last key
    pin["interpolation"] = "smooth"
    for t, key in zip(pin["key_times"], pin["key_offsets"]):
        np.testing.assert_allclose(path_position(pin, x0, t), key, atol=1e-15)
    d = 1e-6
    slope = (path_position(pin, x0, 1.0 + d) - path_position(pin, x0, 1.0 - d)) / (2 * d)
    np.testing.assert_allclose(slope, (np.array([1, 2, 0]) - 0.0) / 3.0, atol=1e-6)
    spin = {"center": np.array([1.0, 0, 0]), "velocity": np.array([0, 0, 2.0]), "spin": np.array([0, np.pi, 0]),
            "key_times": [], "key_offsets": [], "interpolation": "linear"}
    np.testing.assert_allclose(path_position(spin, np.array([2.0, 0, 0]), 1.0), [0, 0, 2.0], atol=1e-12)


def test_pinned_particles_take_no_contact():
    """A held particle below a plane stays where it is (the contact response skips inverse mass 0)."""
    b = ss.ModelBuilder(gravity=(0.0, -9.8, 0.0))
    start = b.add_particles([(0.0, -0.05, 0.0)], [(0.0, 0.0, 0.0)], 0.1)
    b.add_pin([start])
    b.add_plane((0, 0, 0), (0, 1, 0), 0.5, 0.3)
    model = b.finalize("cpu", "float64")
    assert model.pins is None  # held pins launch nothing
    for method in METHODS:
        stepper = ss.Stepper(model, ss.make_integrator(method, model), 1e-3)
        stepper.advance(50)
        np.testing.assert_array_equal(stepper.state.particle_q.numpy()[0], [0.0, -0.05, 0.0])


def test_hang_scene_handle_follows_keyframes():
    """The built-in scene: the top face is exactly on the keyframed path at every written frame."""
    scene = ss.load_scene("hang", ["jelly.0.resolution=4", "simulation.duration=1.5"])
    model = ss.build_model(scene, "cpu")
    sim = ss.Simulator(model, ss.make_integrator("symplectic", model), scene.sim["dt"], scene.sim["fps"],
                       scene.frame_count())
    frames = []

    class Keep:
        def write_frame(self, k, t, q, metrics):
            frames.append((t, np.array(q)))

    result = sim.run([Keep()])
    assert not result.exploded
    pin = scene.data["pin"][0]
    keys = {"center": np.zeros(3), "velocity": np.zeros(3), "spin": np.zeros(3),
            "key_times": [k["time"] for k in pin["keyframes"]], "key_offsets": [k["offset"] for k in pin["keyframes"]],
            "interpolation": pin["interpolation"]}
    held = np.asarray(pin["indices"])
    x0 = model.particle_q_host[held]
    for t, q in frames:
        np.testing.assert_allclose(q[held], x0 + path_position(keys, np.zeros(3), t), rtol=0, atol=2e-6)


@pytest.mark.parametrize(
    "pin, needle",
    [
        ({}, "pin.0.face: give exactly one of face, box and particles"),
        ({"face": "+y", "particles": [0]}, "pin.0.face: give exactly one of face, box and particles"),
        ({"face": "top"}, "pin.0.face: must be one of -x, +x, -y, +y, -z, +z"),
        ({"jelly": 3, "face": "+y"}, "pin.0.jelly: the scene has jellies 0 to 0"),
        ({"particles": [0, 64]}, "pin.0.particles: indices must be below the jelly's 64 particles"),
        ({"box": {"min": [5, 5, 5], "max": [6, 6, 6]}}, "pin.0.box: selects no particle"),
        ({"face": "+y", "keyframes": [{"time": 1.0, "offset": [0, 0, 0]}, {"time": 1.0, "offset": [1, 0, 0]}]},
         "pin.0.keyframes: times must be strictly increasing"),
        ({"face": "+y", "interpolation": "cubic"}, "pin.0.interpolation: must be one of linear, smooth"),
    ],
)
def test_bad_pins_are_one_line_scene_errors(pin, needle):
    data = {"simulation": {"duration": 1.0}, "jelly": [{"resolution": 4, "size": 0.3, "total_mass": 1.0}], "pin": [pin]}
    with pytest.raises(SceneError) as e:
        ss.scene_from_dict(data)
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_pins_through_set_overrides():
    """`--set` reaches pin keys like any other: the hang scene's handle held instead of driven."""
    scene = ss.load_scene("hang", ["pin.0.keyframes=[]", "jelly.0.resolution=4"])
    model = ss.build_model(scene, "cpu")
    assert model.pins is None and model.pinned_count == 16

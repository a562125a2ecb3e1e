"""The API's frame stepper: captured-graph replay steps exactly as launching the steps one by one."""

import numpy as np
import pytest

import softsim_warp as ss


@pytest.mark.parametrize("method", ["rk4", "implicit"])
def test_graph_replay_equals_plain_steps(device, method):
    """``Stepper.advance`` with graph capture (the default) gives the bits of plain stepping, from the
    first call on: the warm-up step loads every kernel before the first capture (without it the
    implicit integrator's conditional nodes, captured while its kernels load, went wrong on the CPU:
    the jelly collapsed onto the plane). The jelly lands within the run, so contact acts."""
    scene = ss.load_scene("jelly_drop", ["jelly.0.resolution=[4,4,4]", "jelly.0.center=[0.0,0.45,0.0]"])
    dt = scene.sim["dt"]
    finals = {}
    for use_graph in (True, False):
        model = ss.build_model(scene, device=device)
        stepper = ss.Stepper(model, ss.make_integrator(method, model), dt, use_graph=use_graph)
        start = stepper.state.particle_q.numpy().copy()
        for _ in range(6):
            stepper.advance(100)
        finals[use_graph] = stepper.state.particle_q.numpy()
    # The jelly fell (0.28 m freely in 0.24 s) and came to rest on the plane at y = 0.
    lowest = finals[False][:, 1].min()
    assert -0.02 < lowest < start[:, 1].min() - 0.05
    if device.is_cpu:
        assert np.array_equal(finals[True], finals[False])
    else:  # a graph replays the same kernels; on CUDA the solver's reductions are atomic
        np.testing.assert_allclose(finals[True], finals[False], atol=1e-4)


def test_stepper_state_can_be_written_between_calls():
    """A captured graph reads the current state buffer, so a write between calls takes effect."""
    model = ss.ModelBuilder(gravity=(0.0, -9.8, 0.0))
    model.add_particles([[0.0, 1.0, 0.0]], [[0.0, 0.0, 0.0]], 1.0)
    model = model.finalize(device="cpu")
    stepper = ss.Stepper(model, ss.make_integrator("symplectic", model), 1.0e-3)
    stepper.advance(100)
    q = stepper.state.particle_q.numpy()
    # Symplectic Euler from rest: y_n = y_0 - g h^2 n (n + 1) / 2.
    assert q[0, 1] == pytest.approx(1.0 - 9.8 * 1.0e-6 * 100 * 101 / 2, abs=1e-6)
    stepper.state.particle_q.assign(np.array([[0.0, 5.0, 0.0]], dtype=np.float32))
    stepper.state.particle_qd.zero_()
    stepper.advance(100)
    assert stepper.state.particle_q.numpy()[0, 1] == pytest.approx(5.0 - 9.8 * 1.0e-6 * 100 * 101 / 2, abs=1e-5)


@pytest.mark.parametrize("method", ["symplectic", "implicit"])
def test_states_of_another_device_or_size_are_refused(method):
    """A state whose arrays live elsewhere than the model, or hold another particle count, is a clear
    error, not a launch that reads out of place (a CPU launch on CUDA arrays crashed the process)."""
    from types import SimpleNamespace

    model = ss.build_model(ss.load_scene("jelly_drop", ["jelly.0.resolution=[3,3,3]"]), device="cpu")
    integrator = ss.make_integrator(method, model)
    good = model.state()
    elsewhere = SimpleNamespace(
        particle_q=SimpleNamespace(device="cuda:0", shape=(27,)), particle_qd=SimpleNamespace(device="cuda:0", shape=(27,))
    )
    with pytest.raises(ValueError, match=r"state_out.particle_q is on cuda:0, the model on cpu"):
        integrator.step(good, elsewhere, 1e-3)
    small = ss.build_model(ss.load_scene("jelly_drop", ["jelly.0.resolution=[2,2,2]"]), device="cpu").state()
    with pytest.raises(ValueError, match="state_in.particle_q has 8 particles, the model 27"):
        integrator.step(small, good, 1e-3)

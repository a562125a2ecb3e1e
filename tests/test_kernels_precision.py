"""kernels/precision.py: a generic kernel's two overloads, launched in one captured graph, each replay
their own function (a float32 run and its float64 reference are measured in one graph)."""

import numpy as np
import warp as wp

from softsim_warp.kernels.precision import Float, both_precisions


@both_precisions
@wp.kernel
def scale_and_shift(a: wp.array(dtype=Float), scale: Float, out: wp.array(dtype=Float)):
    i = wp.tid()
    out[i] = a[i] * scale + type(scale)(1.0)


def test_overloads_have_keys_of_their_own():
    keys = sorted(o.key for o in scale_and_shift.overloads.values())
    assert keys == ["scale_and_shift_float32", "scale_and_shift_float64"]


def test_both_overloads_replay_right_from_one_graph(device):
    a32 = wp.array(np.arange(5), dtype=wp.float32, device=device)
    a64 = wp.array(np.arange(5) + 10.0, dtype=wp.float64, device=device)
    out32, out64 = wp.zeros_like(a32), wp.zeros_like(a64)

    def launch():
        wp.launch(scale_and_shift, 5, inputs=[a32, wp.float32(2.0)], outputs=[out32], device=device)
        wp.launch(scale_and_shift, 5, inputs=[a64, wp.float64(3.0)], outputs=[out64], device=device)

    launch()  # loads the module before the capture
    with wp.ScopedCapture(device=device, force_module_load=False) as capture:
        launch()
    out32.zero_()
    out64.zero_()
    wp.capture_launch(capture.graph)
    np.testing.assert_array_equal(out32.numpy(), np.arange(5, dtype=np.float32) * 2 + 1)
    np.testing.assert_array_equal(out64.numpy(), (np.arange(5) + 10.0) * 3 + 1)

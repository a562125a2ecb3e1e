"""Moving and animated mesh terrain on CUDA: whether ``wp.Mesh.refit`` can be captured in a graph,
and the keyframed/animated meshes followed on the device (the CPU tests' checks, on ``cuda:0``).

    python benchmarks/check_moving_mesh_cuda.py OUT_DIR
"""

import importlib.util
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

import softsim_warp as ss
from softsim_warp.core.mesh_assets import MeshAsset

ROOT = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("make_assets", ROOT / "assets" / "make_assets.py")
MA = importlib.util.module_from_spec(spec)
spec.loader.exec_module(MA)


@wp.kernel
def lift(points: wp.array(dtype=wp.vec3), dy: float):
    i = wp.tid()
    points[i] = points[i] + wp.vec3(0.0, dy, 0.0)


@wp.kernel
def query(mesh: wp.uint64, p: wp.vec3, out: wp.array(dtype=float)):
    q = wp.mesh_query_point_no_sign(mesh, p, 0.5)
    if q.result:
        out[0] = wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
    else:
        out[0] = -1.0


def refit_capture(device):
    """Capture (lift the points 1 m, refit, query within 0.5 m of a point 3.25 m above the sheet)
    and replay it 3 times: the third replay finds the sheet 0.25 m away only if its BVH was refit
    (stale bounds at y = 0 are out of reach), that is when the refit is part of the graph."""
    pts = wp.array(np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], dtype=np.float32), dtype=wp.vec3,
                   device=device)
    mesh = wp.Mesh(points=pts, indices=wp.array(np.array([0, 1, 2, 0, 2, 3], dtype=np.int32), device=device))
    out = wp.zeros(1, dtype=float, device=device)
    wp.launch(lift, dim=4, inputs=[pts, 0.0], device=device)
    wp.launch(query, dim=1, inputs=[mesh.id, wp.vec3(0.0, 3.25, 0.0), out], device=device)
    try:
        with wp.ScopedCapture(device=device, force_module_load=False) as cap:
            wp.launch(lift, dim=4, inputs=[pts, 1.0], device=device)
            mesh.refit()
            wp.launch(query, dim=1, inputs=[mesh.id, wp.vec3(0.0, 3.25, 0.0), out], device=device)
    except Exception as e:  # noqa: BLE001 - reported
        return {"captured": False, "error": f"{type(e).__name__}: {e}"}
    seen = []
    for _ in range(3):
        wp.capture_launch(cap.graph)
        seen.append(float(out.numpy()[0]))
    return {"captured": True, "distances_after_replays": seen, "refit_in_graph": seen == [-1.0, -1.0, 0.25]}


def follow(device, tmp):
    plate = Path(tmp) / "plate.usda"
    MA.write_animated_plate(plate)
    res = {}
    for precision in ("float32", "float64"):
        sc = ss.scene_from_dict({
            "simulation": {"integrator": "symplectic", "dt": 1e-3, "duration": 1.0, "precision": precision},
            "jelly": [{"resolution": 3, "size": 0.1, "center": [0.0, 0.06, 0.0], "particle_mass": 0.01}],
            "mesh": [{"path": str(plate), "animated": True, "friction": 0.8, "restitution": 0.0}],
        })
        model = ss.build_model(sc, device)
        st = ss.Stepper(model, ss.make_integrator("symplectic", model), 1e-3)
        worst = 0.0
        t0 = time.perf_counter()
        for k in range(900):
            st.advance(1)
            if k % 9 == 0:
                worst = max(worst, float(np.abs(st.integrator.run.meshes.mesh_points.numpy() - MA.animated_plate_world((k + 1) * 1e-3)).max()))
        wall = time.perf_counter() - t0
        v = st.state.particle_qd.numpy()
        bottom = np.argsort(st.state.particle_q.numpy()[:, 1])[:9]
        res[f"animated_{precision}"] = {"worst_point_error_m": worst, "graph": st.use_graph,
                                        "bottom_vx": float(v[bottom, 0].mean()), "wall_s_900_steps": wall}
        # A platform mesh moving at 1 m/s, captured in graphs: the jelly rides it.
        quad = MeshAsset(np.array([[-4, 0, -4], [-4, 0, 4], [4, 0, 4], [4, 0, -4]], float),
                                             np.array([4]), np.array([0, 1, 2, 3]))
        b = ss.ModelBuilder()
        b.add_jelly((3, 3, 3), (0.1, 0.1, 0.1), 0.01, {n: {"ks": 1000.0, "kd": 0.5} for n in ("structural", "shear", "bending")},
                    center=(0.0, 0.05, 0.0))
        b.add_mesh(quad, restitution=0.0, friction=0.8, motion={"velocity": (1.0, 0.0, 0.0)})
        m2 = b.finalize(device, precision)
        st2 = ss.Stepper(m2, ss.make_integrator("symplectic", m2), 2e-4)
        st2.advance(2500)
        res[f"platform_{precision}"] = {"graph": st2.use_graph, "vx_mean_at_0.5s": float(st2.state.particle_qd.numpy()[:, 0].mean()),
                                        "min_y": float(st2.state.particle_q.numpy()[:, 1].min())}
    return res


if __name__ == "__main__":
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    device = "cuda:0" if wp.get_cuda_device_count() else "cpu"
    result = {"device": str(wp.get_device(device)), "refit_capture": refit_capture(device)}
    with tempfile.TemporaryDirectory() as tmp:
        result.update(follow(device, tmp))
    print(json.dumps(result, indent=1))
    (out / f"moving_mesh_{device.replace(':', '')}.json").write_text(json.dumps(result, indent=1))

"""Cost of a mesh jelly per particle-step against a box jelly of (about) the same particle count.

Run::

    python benchmarks/bench_mesh_jelly.py --device cpu --res 12 20 --json bench_mesh_jelly_cpu.json
    python benchmarks/bench_mesh_jelly.py --device cuda:0 --res 20 40 80 --json bench_mesh_jelly_cuda.json
    python benchmarks/bench_mesh_jelly.py --device cpu --res 12 20 --contact --load 20000 60000 125000 250000 --json ...

For each resolution R a sphere mesh (and a torus) is voxelised into a jelly of R cells across
(``[[jelly]] mesh = ...``), the sphere on the masked-lattice path (the CUDA default,
core/masked_lattice.py; forced here on the CPU too) with its fused stage (``*_fused``: the CUDA
default, core/fused.py) and unfused (``sphere_masked``: force kernel, then the update), and on the
spring list, the torus on the fused masked path; and a box jelly with the nearest cube of the same
particle count is built on the lattice path (the default for a box; ``box_generic``: its generic
stage) and on the spring list. Each model is compiled and warmed up, then ``--steps`` steps
of ``--integrator`` are timed ``--repeats`` times (on CUDA one captured graph, wall time; on the CPU
launch by launch, this thread's CPU time). The table gives the median time per particle-step
and the ratio of each case to the box on the lattice path (``x box lattice``: the box of the
sphere's count; ``x box same N``: the box of the case's own count, the torus's for the torus), the
goal's measure (a mesh jelly within 1.5x of a full box of the same particle count). Compile time
is recorded apart. Nothing here is asserted.

``--contact``: the critter asset (thin legs and ears) resting on a plane at each resolution, on its
default path and on the fused masked path, against a box jelly of (about) its particle count on the
same plane (``x box same N``: the issue's measure for the step with contact). ``--load``: the CPU seconds
from a scene naming a new mesh file (.usdc) to its validated jelly (read, weld, voxelise, embed).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from softsim_warp.core.model import ModelBuilder, populate
from softsim_warp.core.terrain import sphere_mesh
from softsim_warp.io.scene import scene_from_dict
from softsim_warp.studies.bench import IntegratorCase

SPRINGS = {"structural": {"ks": 50.0, "kd": 0.1}, "shear": {"ks": 50.0, "kd": 0.1}, "bending": {"ks": 25.0, "kd": 0.05}}


def write_usd(path, points, counts, indices):
    from pxr import Usd, UsdGeom, Vt  # noqa: PLC0415

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    m = UsdGeom.Mesh.Define(stage, "/Asset")
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(points, dtype=np.float32)))
    m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.asarray(counts, dtype=np.int32)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(indices, dtype=np.int32)))
    stage.GetRootLayer().Save()
    return str(path)


def torus_mesh(R=1.0, r=0.45, nu=96, nv=48):
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    U, V = np.meshgrid(u, v, indexing="ij")
    pts = np.stack([(R + r * np.cos(V)) * np.cos(U), r * np.sin(V), (R + r * np.cos(V)) * np.sin(U)], -1).reshape(-1, 3)
    idx = []
    for i in range(nu):
        for j in range(nv):
            a, b = i * nv + j, ((i + 1) % nu) * nv + j
            c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
            idx += [a, d, c, b]
    return pts, np.full(nu * nv, 4), np.array(idx)


def scene(jelly):
    j = {"center": [0.0, 5.0, 0.0], "total_mass": 1.0, "springs": SPRINGS, **jelly}
    return scene_from_dict({"simulation": {"dt": 1e-4, "frames": 1}, "jelly": [j]})


class Case(IntegratorCase):
    """One model and integrator, warmed up, that times ``steps`` steps (a captured graph on CUDA)."""

    def __init__(self, name, scn, device, integrator, steps, dt=1e-4, force_path="auto", gather=False, **options):
        import warp as wp  # noqa: PLC0415

        self.name = name
        builder = ModelBuilder(scn.sim["gravity"])
        builder.device = device
        populate(builder, scn.data)
        # gather: the masked path on any device (finalize takes it on CUDA only).
        model = builder.finalize(device, scn.sim["precision"], force_path=force_path,
                                 masked_kernel="gather" if gather else None)
        self.particles = model.particle_count
        self.path = "lattice" if model.lattice is not None else "masked" if model.masked is not None else "springs"
        # options: the fused stage's (fused, single; core/fused.py configure_fused); none: the defaults.
        super().__init__(model, integrator, dt, steps, use_graph=wp.get_device(device).is_cuda, options=options)
        if self.integrator.fused:
            self.path += " fused" + (" 1" if self.integrator.single else "")
        self.compile_seconds = self.prepare()

    def time(self) -> float:
        """Seconds per step (CUDA: wall; CPU: this thread's CPU time)."""
        self.time_once()
        return (self.wall[-1] if self.use_graph else self.thread[-1]) / self.steps


def _make_assets():
    import importlib.util  # noqa: PLC0415

    spec = importlib.util.spec_from_file_location("make_assets", Path(__file__).resolve().parents[1] / "assets" / "make_assets.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def contact_rows(args) -> list:
    """The critter (scenes/assets/critter.usda: thin legs and ears) resting on a plane at each
    resolution, on its default path and on the fused masked path, against a box jelly of (about) its
    particle count on the same plane (its default path, the lattice): the step with contact."""
    rows = []
    plane = [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0], "restitution": 0.2, "friction": 0.5}]
    critter = str(Path(__file__).resolve().parents[1] / "scenes" / "assets" / "critter.usda")
    for res in args.res:
        def on_plane(jelly, y):
            j = {"center": [0.0, y, 0.0], "total_mass": 1.0, "springs": SPRINGS, **jelly}
            return scene_from_dict({"simulation": {"dt": 1e-4, "frames": 1}, "jelly": [j], "plane": plane})

        mesh = on_plane({"mesh": critter, "resolution": res}, 0.32 + 1e-4)  # its feet (and lowest particles) on the plane
        dev, method, steps = args.device, args.integrator, args.steps
        cases = [Case("critter_contact", mesh, dev, method, steps),
                 Case("critter_contact_fused", mesh, dev, method, steps, gather=True)]
        n = round(cases[0].particles ** (1.0 / 3.0))
        cases.append(Case("box_contact", on_plane({"resolution": [n, n, n], "size": 0.6}, 0.3 + 1e-4), dev, method, steps))
        times = {c.name: [] for c in cases}
        for _ in range(args.repeats):
            for c in cases:
                times[c.name].append(c.time())
        ref = statistics.median(times["box_contact"]) / cases[2].particles
        for c in cases:
            per = statistics.median(times[c.name]) / c.particles
            rows.append({
                "res": res, "case": c.name, "path": c.path, "particles": c.particles,
                "seconds_per_step": statistics.median(times[c.name]), "ns_per_particle_step": per * 1e9,
                "ratio_to_box_lattice": per / ref, "ratio_to_box_same_count": per / ref,
                "compile_seconds": c.compile_seconds,
            })
    return rows


def load_rows(sizes) -> list:
    """CPU seconds from a scene naming a new mesh file to its validated jelly (read, weld and edge count,
    voxelise, cells, embedding): the blob of make_assets at about ``sizes`` vertices, as .usdc, at 12
    cells along its longest side. One small asset is loaded first (USD's and Warp's start-up)."""

    mk = _make_assets()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, target in enumerate([1000] + list(sizes)):
            segments = max(8, int(round(np.sqrt(2.0 * target))))
            pts, counts, idx, _ = mk.lat_long(mk.blob_radius, rings=max(4, segments // 2), segments=segments)
            path = write_usd(Path(tmp) / f"blob{k}.usdc", pts, counts, idx)
            t0 = time.process_time()  # this process's CPU time (all its threads): others' load does not count
            scn = scene({"mesh": path, "resolution": 12})
            seconds = time.process_time() - t0
            if k:
                j = scn.data["jelly"][0]
                rows.append({"vertices": int(len(pts)), "faces": int(len(counts)),
                             "lattice_points": int(np.prod(j["resolution"])), "particles": None, "seconds": seconds})
                from softsim_warp.core.voxelize import mesh_lattice  # noqa: PLC0415

                rows[-1]["particles"] = int(mesh_lattice(j)[1].sum())
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--res", type=int, nargs="+", default=[12, 20])
    ap.add_argument("--integrator", default="symplectic")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", default=None)
    ap.add_argument("--contact", action="store_true",
                    help="also the step with contact: the critter mesh jelly on a plane against a box jelly of its count")
    ap.add_argument("--load", type=int, nargs="*", default=None, metavar="VERTICES",
                    help="also the loading time (read, voxelise, embed) of assets of about these vertex counts")
    args = ap.parse_args(argv)
    import warp as wp  # noqa: PLC0415

    wp.config.quiet = True
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        sphere = write_usd(Path(tmp) / "sphere.usda", *sphere_mesh([0, 0, 0], 1.0, rings=48, segments=96))
        torus = write_usd(Path(tmp) / "torus.usda", *torus_mesh())
        for res in args.res:
            sphere_scene = scene({"mesh": sphere, "resolution": res, "size": 1.0})
            dev, method, steps = args.device, args.integrator, args.steps
            cases = [
                Case("sphere_fused", sphere_scene, dev, method, steps, gather=True),
                Case("sphere_masked", sphere_scene, dev, method, steps, gather=True, fused=False),
                Case("sphere_springs", sphere_scene, dev, method, steps, force_path="springs"),
                Case("torus_fused", scene({"mesh": torus, "resolution": res, "size": 1.0}), dev, method, steps,
                     gather=True),
            ]
            n = round(cases[0].particles ** (1.0 / 3.0))
            box = scene({"resolution": [n, n, n], "size": 1.0})
            cases.append(Case("box_lattice", box, dev, method, steps))
            cases.append(Case("box_generic", box, dev, method, steps, single=False))
            cases.append(Case("box_springs", box, dev, method, steps, force_path="springs"))
            # The torus has fewer particles than the sphere: its own box of (about) its count too.
            nt = round(cases[3].particles ** (1.0 / 3.0))
            cases.append(Case("box_torus_count", scene({"resolution": [nt, nt, nt], "size": 1.0}), dev, method, steps))
            by_name = {c.name: c for c in cases}
            times = {c.name: [] for c in cases}
            for _ in range(args.repeats):
                for c in cases:  # interleaved, so drifts of the machine hit every case alike
                    times[c.name].append(c.time())

            def per_particle(name):
                return statistics.median(times[name]) / by_name[name].particles

            ref = per_particle("box_lattice")
            for c in cases:
                per = per_particle(c.name)
                # The measure: against a box of the same particle count on its default path.
                same = per_particle("box_torus_count" if "torus" in c.name else "box_lattice")
                rows.append({
                    "res": res, "case": c.name, "path": c.path, "particles": c.particles,
                    "seconds_per_step": statistics.median(times[c.name]), "ns_per_particle_step": per * 1e9,
                    "ratio_to_box_lattice": per / ref, "ratio_to_box_same_count": per / same,
                    "compile_seconds": c.compile_seconds,
                })
        if args.contact:
            rows += contact_rows(args)
    load = load_rows(args.load) if args.load else []
    print(f"{'res':>4} {'case':<21} {'path':<16} {'particles':>9} {'ns/particle-step':>17} {'x box lattice':>14}"
          f" {'x box same N':>13}")
    for r in rows:
        print(f"{r['res']:>4} {r['case']:<21} {r['path']:<16} {r['particles']:>9} {r['ns_per_particle_step']:>17.2f} "
              f"{r['ratio_to_box_lattice']:>14.2f} {r['ratio_to_box_same_count']:>13.2f}")
    if load:
        print(f"\n{'vertices':>9} {'faces':>9} {'lattice points':>15} {'particles':>9} {'load s':>8}")
        for r in load:
            print(f"{r['vertices']:>9} {r['faces']:>9} {r['lattice_points']:>15} {r['particles']:>9} {r['seconds']:>8.3f}")
    if args.json:
        meta = {"device": str(wp.get_device(args.device)), "integrator": args.integrator, "steps": args.steps,
                "repeats": args.repeats, "warp": wp.config.version}
        Path(args.json).write_text(json.dumps({"meta": meta, "rows": rows, "load": load}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

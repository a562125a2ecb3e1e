"""The cost of contact between jellies, against Newton's particle contact (``softsim bench --contact``).

A pile of jellies (``--contact-size``^3 particles each, the ``bench`` jelly's spacing, mass and
springs: :class:`~softsim_warp.studies.bench.JellySpec`) stands on a ground plane as a block of
``k x k x k`` cells, first the bottom layer; every other layer is shifted by half a spacing so that
particles do not sit on each other, and neighbouring jellies are 0.85 spacings apart, inside both
our pair distance (one spacing) and Newton's (2 x 0.45 spacings): every face of the block touches
its neighbour's from the first step. For each count in ``--jellies`` the command times:

* ours without jelly contact (``jelly_contact = false``), the same particles and springs;
* ours with it (surface normals, the candidate lists and their rebuilds, the contacts,
  ``jelly_contact_iterations`` velocity passes, the last with the positions' projection, every step);
* with ``--peer newton``: Newton 1.8's ``SolverSemiImplicit`` on the same springs and ground, once
  without particle contact (``model.particle_grid = None``) and once with it (its ``HashGrid``
  rebuilt every step by the solver, penalty forces ``particle_ke/kd/kf/mu``; particle radius 0.45
  spacings, so that a jelly's own neighbours, one spacing apart, do not touch: Newton has no
  exclusion of a body's own particles).

Timing as ``softsim bench``: one untimed step, ``--steps`` steps captured as a graph (CPU and CUDA)
and replayed ``--repeats`` times, the median reported; the cases of one count run their repeats in
turn (:func:`measure`). The table (:func:`format_table`) gives ms per step, particle-steps/s, and the cost of contact as the ratio of the
step with contact to the step without, for ours and Newton's.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..core.methods import SYMPLECTIC
from ..core.model import ModelBuilder
from ..core.stepper import make_integrator
from .bench_newton import NewtonJelly
from .timing import TimedSteps

# Newton's particle radius in lattice spacings: below 0.5, a jelly's own neighbours never touch.
NEWTON_RADIUS = 0.45
# Distance between neighbouring jellies' facing surfaces, in lattice spacings.
JELLY_GAP = 0.85


def pile_positions(count: int, size: int, spacing: float):
    """Centres of ``count`` jellies of ``size``^3 particles in a block on the ground y = 0 [m]."""
    k = max(1, math.ceil(count ** (1.0 / 3.0) - 1e-9))
    edge = spacing * (size - 1)
    pitch = edge + JELLY_GAP * spacing
    centres = []
    for c in range(count):
        layer, rest = divmod(c, k * k)
        row, col = divmod(rest, k)
        shift = 0.5 * spacing * (layer % 2)
        centres.append(
            (
                (col - 0.5 * (k - 1)) * pitch + shift,
                0.5 * spacing + 0.5 * edge + layer * pitch,
                (row - 0.5 * (k - 1)) * pitch + shift,
            )
        )
    return centres


def build_pile(count, size, spec, device, precision="float32", contact=True):
    """The pile as one model (one world), with or without contact between its jellies."""
    builder = ModelBuilder((0.0, spec.gravity, 0.0))
    springs = {t: {"ks": spec.ks, "kd": spec.kd} for t in ("structural", "shear", "bending")}
    edge = spec.spacing * (size - 1)
    for centre in pile_positions(count, size, spec.spacing):
        builder.add_jelly((size,) * 3, edge, spec.particle_mass, springs, center=centre)
    builder.add_plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), spec.restitution, spec.friction)
    builder.jelly_contact = bool(contact)
    return builder.finalize(device, precision)


class PileCase(TimedSteps):
    """Our integrator on the pile, with contact between jellies (``contact``) or without it.

    Both cases share one model (building a pile of 1,000 jellies takes half a minute); each has its
    own integrator, whose run state holds its contact lists, and the case without contact takes the
    jelly contact hook out of its integrator's hooks.
    """

    def __init__(self, model, method, dt, steps, use_graph, contact):
        self.model = model
        self.integrator = make_integrator(method, model)
        if not contact:
            self.integrator.run.contact_hooks = []
        self.states = [model.state(), model.state()]

        def step(count):
            for k in range(count):
                self.integrator.step(self.states[k % 2], self.states[1 - k % 2], dt)

        super().__init__(model.device, step, steps, use_graph)

    def positions(self):
        return self.states[0].particle_q.numpy()


class NewtonPileCase(TimedSteps):
    """Newton's ``SolverSemiImplicit`` on the pile's springs and ground, with or without its particle contact."""

    def __init__(self, model, spec, steps, use_graph, contact):
        import warp as wp  # noqa: PLC0415

        t0 = time.perf_counter()
        radius = NEWTON_RADIUS * spec.spacing
        self.jelly = NewtonJelly(
            model.particle_q_host,
            model.spring_indices_host,
            model.spring_rest_host,
            model.spring_stiffness_host,
            model.spring_damping_host,
            model.particle_mass_host,
            model.gravity_host,
            0.0,
            model.device,
            particle_radius=radius,
            contact_mu=spec.friction,
        )
        if contact:
            m = self.jelly.model
            # Newton's own default grid (128^3 cells), on the model's device; the solver reserves it
            # and rebuilds it every step with the search radius 2 r.
            m.particle_grid = wp.HashGrid(128, 128, 128, device=model.device)
            m.particle_ke, m.particle_kd, m.particle_kf, m.particle_mu = 1.0e3, 1.0, 10.0, spec.friction
            self.jelly.solver = self.jelly.newton.solvers.SolverSemiImplicit(m)
        self.build_s = time.perf_counter() - t0
        super().__init__(model.device, lambda count: self.jelly.step(spec.dt, count), steps, use_graph)

    def positions(self):
        return self.jelly.positions()


def measure(counts, size, methods, spec, device, *, precision="float32", steps=200, repeats=7, use_graph=True,
            peer=False):
    """Rows of ms per step with and without contact, per pile of ``counts`` jellies of ``size``^3 particles.

    Each integrator of ``methods`` runs with and without contact on one model per count; with
    ``peer``, Newton's ``SolverSemiImplicit`` does too (for ``symplectic``, the method it matches).
    """
    import warp as wp  # noqa: PLC0415

    rows = []
    for count in counts:
        t0 = time.perf_counter()
        model = build_pile(count, size, spec, device, precision, contact=True)
        build_s = time.perf_counter() - t0
        for method in methods:
            cases = {}
            for contact in (False, True):
                cases[("ours", contact)] = PileCase(model, method, spec.dt, steps, use_graph, contact)
                cases[("ours", contact)].build_s = build_s
            if peer and method == SYMPLECTIC.name:  # Newton's SemiImplicitIntegrator is symplectic Euler
                for contact in (False, True):
                    cases[("newton", contact)] = NewtonPileCase(model, spec, steps, use_graph, contact)
            first = {key: case.prepare() for key, case in cases.items()}
            for _ in range(repeats):
                for case in cases.values():
                    case.time_once()
            particles = model.particle_count
            hook = model.particle_contact  # the contact particles (the lists are each case's)
            for (who, contact), case in cases.items():
                ms = case.ms_per_step()
                base = cases[(who, False)].ms_per_step()
                rows.append(
                    {
                        "jellies": count,
                        "particles": particles,
                        "contact_particles": hook.count if who == "ours" else particles,
                        "solver": method if who == "ours" else "newton.SolverSemiImplicit",
                        "contact": contact,
                        "ms_per_step": ms,
                        "particle_steps_per_s": particles * 1e3 / ms,
                        "contact_cost": ms / base,
                        "first_step_s": first[(who, contact)],
                        "build_s": getattr(case, "build_s", None),
                        "finite": bool(np.all(np.isfinite(case.positions()))),
                        "graph": use_graph,
                    }
                )
                if who == "ours" and contact:
                    # Candidate-list builds over every step this case ran (first steps, warm-up,
                    # repeats): how often the skin ran out.
                    rows[-1]["list_builds"] = case.integrator.run.particle_contact.builds_done()
                    rows[-1]["steps_run"] = 2 + case.steps * (1 + repeats)
            for case in cases.values():
                case.graph = None
            del cases
        del model
        wp.synchronize_device(device)
    return rows


def format_table(rows, device_name, spec, size, steps, repeats) -> str:
    """The rows of :func:`measure` as ``softsim bench --contact`` prints them."""
    lines = [f"bench --contact on {device_name}: piles of {size}^3-particle jellies, dt {spec.dt:g} s, "
             f"{steps} steps x {repeats} repeats (median)"]
    header = f"{'jellies':>7} {'particles':>10} {'solver':<27} {'contact':<7} {'ms/step':>9} {'particle-steps/s':>17} {'x no-contact':>12}"
    lines += [header, "-" * len(header)]
    for r in rows:
        flag = "" if r["finite"] else "  NOT FINITE"
        lines.append(
            f"{r['jellies']:>7} {r['particles']:>10} {r['solver']:<27} {('yes' if r['contact'] else 'no'):<7} "
            f"{r['ms_per_step']:>9.4f} {r['particle_steps_per_s']:>17.3e} {r['contact_cost']:>12.2f}{flag}"
        )
    for r in rows:
        if "list_builds" in r:
            lines.append(f"{r['jellies']} jellies: candidate lists built {r['list_builds']} times in {r['steps_run']} steps")
    return "\n".join(lines)

"""Internal forces: springs and dampers, one entry point (:func:`eval_forces`) and its paths.

A model takes one of three force paths, chosen when it is finalised and never per call:

* lattice (``core/lattice_model.py``, ``kernels/lattice.py``): a jelly built as a regular lattice
  stores no spring index arrays; each particle gathers its springs from the lattice stencil (CUDA)
  or each jelly runs its row loops (CPU). No atomics, so it is deterministic as it stands.
* spring list, atomic: one thread per spring adds its force to both particles with atomics; any
  topology (``kernels/springs.py``). Fastest for a general spring list, but the order of the
  atomic adds, and so the float sum, varies from run to run on CUDA.
* spring list, deterministic (``softsim run --deterministic``): one thread per spring writes its
  force, then one thread per particle sums its incident springs in ascending spring order from a
  CSR list (``ModelBuilder.finalize(deterministic=True)``, :func:`incident_springs_csr`),
  bitwise-identical from run to run on CUDA as on the CPU.

Determinism is this property of the force path; the per-frame metrics have their own fixed-order
reduction (``io/metrics.py``). The implicit integrator's solver reductions are not covered.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .lattice_model import eval_lattice_forces
from .masked_lattice import eval_masked_forces


def incident_springs_csr(pairs: np.ndarray, particle_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Each particle's incident springs in ascending spring order, as CSR.

    Args:
        pairs: ``(S, 2)`` particle indices of the springs.
        particle_count: number of particles N.

    Returns:
        ``(offsets (N + 1,), entries (2 S,))`` int32: the entries of particle i are
        ``entries[offsets[i]:offsets[i + 1]]``; entry ``s`` means i is the first particle of spring
        s, ``-(s + 1)`` the second.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    s = np.arange(pairs.shape[0], dtype=np.int64)
    # Interleave (a_0, b_0, a_1, b_1, ...) so that a stable sort by particle keeps ascending spring
    # order, with a spring's first particle before its second: the order of the atomic kernel.
    particle = pairs.reshape(-1)
    code = np.stack([s, -(s + 1)], axis=1).reshape(-1)
    order = np.argsort(particle, kind="stable")
    counts = np.bincount(particle, minlength=particle_count)
    offsets = np.zeros(particle_count + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    if offsets[-1] > np.iinfo(np.int32).max:
        raise ValueError("too many springs for an int32 CSR list")
    return offsets.astype(np.int32), code[order].astype(np.int32)


class ForceWork:
    """The scratch a force evaluation writes (part of a ``RunState``; ``eval_forces``'s ``work``).

    Attributes:
        spring_force: deterministic spring list: each spring's force on its first particle [N],
            shape [spring_count], vec3; None on the other paths.
        lattice_scratch: the CPU row kernel's workspace (``kernels/lattice.py``), shape
            [particle_count], vec3; None unless the lattice path runs the row kernel
            (``LatticeData.kernel`` when this is made).
    """

    def __init__(self, model):
        lat = model.lattice
        self.spring_force = None
        if model.deterministic and lat is None and model.masked is None:
            self.spring_force = wp.zeros(model.spring_count, dtype=model.vec3, device=model.device)
        self.lattice_scratch = None
        if lat is not None and lat.kernel == "rows":
            self.lattice_scratch = wp.empty(model.particle_count, dtype=lat.layout_vec3, device=model.device)


def _spring_inputs(model, q: wp.array, qd: wp.array) -> list:
    """The spring list and the state, in the order both spring-force kernels take them."""
    return [model.spring_indices, model.spring_rest_length, model.spring_stiffness, model.spring_damping, q, qd]


def _eval_spring_forces_gathered(model, q: wp.array, qd: wp.array, f_out: wp.array, work: ForceWork):
    """Spring and damper forces of (q, qd) into ``f_out`` without atomics; every entry is written."""
    k = model.kernels
    if model.spring_count:
        wp.launch(
            k.eval_spring_forces,
            dim=model.spring_count,
            inputs=_spring_inputs(model, q, qd),
            outputs=[work.spring_force],
            device=model.device,
        )
    wp.launch(
        k.gather_spring_forces,
        dim=model.particle_count,
        inputs=[model.spring_csr_offsets, model.spring_csr_springs, work.spring_force],
        outputs=[f_out],
        device=model.device,
    )


def eval_forces(model, q: wp.array, qd: wp.array, f_out: wp.array, work: ForceWork | None = None):
    """Internal forces (springs and dampers) of the state (q, qd) into ``f_out``; gravity is added as an acceleration.

    ``work``: the scratch the force path writes, an integrator's ``run.forces``; None makes one for
    this call (allocating, so not inside a graph capture: tests and one-off evaluations).
    """
    if work is None:
        work = ForceWork(model)
    if model.masked is not None:
        # Masked lattice (mesh jellies, core/masked_lattice.py): the stencil gathered per particle.
        eval_masked_forces(model, q, qd, f_out)
        return
    if model.lattice is not None:
        # Regular lattice: springs implicit in the lattice, each particle's force gathered (no atomics).
        eval_lattice_forces(model, q, qd, f_out, work.lattice_scratch)
        return
    if model.deterministic:
        # Spring list, atomic-free: per-spring forces, then a fixed-order gather per particle.
        _eval_spring_forces_gathered(model, q, qd, f_out, work)
        return
    f_out.zero_()
    if model.spring_count:
        wp.launch(
            model.kernels.eval_springs,
            dim=model.spring_count,
            inputs=_spring_inputs(model, q, qd),
            outputs=[f_out],
            device=model.device,
        )

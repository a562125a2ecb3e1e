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

Force terms beyond the springs. The springs are the force of every path: one definition,
``kernels/springs.spring_force``, that the lattice gathers, row loops and native stages call or are
checked against (tests/test_kernels_lattice.py). Any other internal force is a :class:`ForceTerm`
that the model declares when it is built (``ModelBuilder.finalize(force_terms=...)``), and the rule
is: a declared term reaches every path that evaluates forces, or that path refuses the model in one
line. :data:`PATHS_TAKING_FORCE_TERMS` lists the paths that evaluate them (the spring list, atomic
and deterministic: each term's ``add`` launches after the springs); every other path in
:data:`FORCE_PATHS` compiles the spring force into its kernels and is refused where it is chosen,
once: ``finalize`` takes the spring list for a model with force terms (``force_path="lattice"``
raises :class:`ForceTermError`), so the lattice, masked and fused paths never see a term, and the
implicit integrator's constructor calls :func:`check_force_terms`. Adding a term to another path
means implementing it there and listing the path.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .lattice_model import eval_lattice_forces
from .masked_lattice import eval_masked_forces
from ..kernels import springs as springs_kernels


class ForceTerm:
    """An internal force beyond the springs, declared by the model (``Model.force_terms``).

    ``name`` is what a refusal names; :meth:`add` adds the term's force on every particle at the
    state (q, qd) to ``f_out``, with Warp launches only (no host synchronisation, so a step stays
    capturable as a graph), after the springs have been written.
    """

    name = "force term"

    def add(self, model, q: wp.array, qd: wp.array, f_out: wp.array) -> None:
        raise NotImplementedError


class ForceTermError(ValueError):
    """A force path that cannot evaluate a model's force terms refuses it (one line)."""


# Every path that evaluates forces, and those of them that evaluate declared force terms. "lattice"
# is both of its kernels (the CUDA gather and the CPU row loops); "fused stage" every fused explicit
# stage (gather, shape-compiled, masked and rows, core/fused.py).
FORCE_PATHS = ("spring list", "lattice", "masked lattice", "fused stage", "implicit solve")
PATHS_TAKING_FORCE_TERMS = ("spring list",)


def check_force_terms(model, path: str, terms=None) -> None:
    """Raise :class:`ForceTermError` (one line) when ``path`` cannot evaluate the force terms of
    ``model`` (or ``terms``, before the model exists)."""
    if path not in FORCE_PATHS:
        raise ValueError(f"unknown force path {path!r}; choose from {', '.join(FORCE_PATHS)}")
    terms = tuple(model.force_terms if terms is None else terms)
    if terms and path not in PATHS_TAKING_FORCE_TERMS:
        names = ", ".join(repr(term.name) for term in terms)
        raise ForceTermError(
            f"the {path} path evaluates only the springs, not the force term {names}; "
            f"the {' and '.join(PATHS_TAKING_FORCE_TERMS)} path does (force_path='springs')"
        )


def force_path_for_terms(force_path: str, terms) -> str:
    """The force path ``ModelBuilder.finalize`` takes for ``force_path`` given the model's force terms:
    "auto" becomes "springs" when there are terms; "lattice" with terms is refused."""
    if not terms:
        return force_path
    if force_path == "lattice":
        check_force_terms(None, "lattice", terms)
    return "springs"


def _add_force_terms(model, q: wp.array, qd: wp.array, f_out: wp.array) -> None:
    for term in model.force_terms:
        term.add(model, q, qd, f_out)


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
    if model.spring_count:
        wp.launch(
            springs_kernels.eval_spring_forces,
            dim=model.spring_count,
            inputs=_spring_inputs(model, q, qd),
            outputs=[work.spring_force],
            device=model.device,
        )
    wp.launch(
        springs_kernels.gather_spring_forces,
        dim=model.particle_count,
        inputs=[model.spring_csr_offsets, model.spring_csr_springs, work.spring_force],
        outputs=[f_out],
        device=model.device,
    )


def eval_forces(model, q: wp.array, qd: wp.array, f_out: wp.array, work: ForceWork | None = None):
    """Internal forces of the state (q, qd) into ``f_out``: springs and dampers, and the model's force
    terms on the spring list (see the module docstring); gravity is added as an acceleration.

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
    else:
        f_out.zero_()
        if model.spring_count:
            wp.launch(
                springs_kernels.eval_springs,
                dim=model.spring_count,
                inputs=_spring_inputs(model, q, qd),
                outputs=[f_out],
                device=model.device,
            )
    _add_force_terms(model, q, qd, f_out)

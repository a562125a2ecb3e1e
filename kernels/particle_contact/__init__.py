"""Contact between jellies and of a jelly with itself: a post-step projection over candidate lists.

The kernels live in four modules: ``pairs`` (the physics of one pair: may it touch, its normal, its
impulse and position correction), ``candidates`` (the cell grid and the candidate lists),
``response`` (the touching pairs and the Jacobi passes) and ``tables`` (native loads and stores of
the contact tables, and the records the passes exchange). This package exposes each kernel and
constant by name: ``from softsim_warp.kernels import particle_contact``,
``wp.launch(particle_contact.find_particle_contacts, ...)``. Each kernel is a Warp module of its own
(``module="unique"``): the passes launch with a block size of their own, and Warp compiles a
module once for each block size it is launched with.

The response runs after the integrator's step, on its result, like terrain contact
(``core/particle_contact.py`` launches these kernels from ``model.contact_hooks``). Each step:

1. ``prepare_contact_particles`` copies the contact particles' positions, each with its contact
   radius, to a compact array, computes their boundary-face normals, and raises the rebuild flag
   when a particle has moved ``rebuild_distance`` or more since the candidate lists were built;
2. ``insert_contact_grid`` and ``build_contact_candidates`` (they return at once unless the flag is
   raised) rebuild each particle's candidate list: the particles of other jellies (or of its own
   jelly, with self-contact, far enough apart in the rest shape) of its world within the candidate
   reach plus a skin, in ascending index order, found through a hashed cell grid;
3. ``find_particle_contacts`` tests each candidate and stores the touching pairs with their normal,
   gap and, with a restitution above zero, approach speed before the step, each started from the
   pair's impulse of the step before (the warm start), and each particle in contact's record for
   the passes (its velocities after those impulses and before the response, its contacts and its
   inverse mass);
4. ``resolve_contact_velocities`` (Jacobi iterations, the pairs' impulses accumulated over the step;
   one fewer than ``jelly_contact_iterations``) and ``resolve_contact_last_pass`` (the last iteration,
   then the positions and velocities written back, each touching pair's remaining overlap projected
   out) apply them.

Why no contact is missed: a pair is left out of the lists only when its distance at the build was
at least ``CANDIDATE_REACH d + skin``; the lists are rebuilt before any particle has moved
``skin / 2`` (``rebuild_distance`` is slightly less, for the rounding of the distances), so until
then such a pair stays farther apart than ``CANDIDATE_REACH d``, where it is no candidate.

Every pair impulse is computed from the pair's own values only, so particle j receives exactly the
negative of what particle i does: linear momentum is conserved pair by pair. Each thread writes
only its own particle (no atomics in the response) and visits its contacts in ascending index order
of the partner, whatever the grid's or the threads' order: the sum is the same on every run and
device, and it does not depend on when the lists were last built. The grid is built with atomics,
so the order within a cell varies on CUDA; the lists are sorted, so nothing downstream sees it.

Jacobi accumulation with split masses (Tonge et al. 2012, "Mass splitting for jitter-free parallel
rigid body simulation"): a particle in k contacts would be corrected k times over if every pair
acted in full, so each pair's effective mass uses k_i / m_i and k_j / m_j for the inverse masses.
The impulse is still one number applied to both particles with opposite signs, so momentum is
exact (scaling each particle's correction by its own count, as constraint averaging does, would
not be). Iterations of the velocity pass converge towards the coupled solution; the last one also
projects out the overlap each pair expects to keep (:func:`projection_term`). Each pair's impulse
so far is kept: an iteration can take back what an earlier one (or the warm start) gave too much,
down to no push at all, and friction stays within mu times the push over the whole step. Starting
each step from the last one's impulses (Catto's warm starting) lets one iteration hold a resting
stack.
"""

from .candidates import (
    CELL_WRAP,
    FIBONACCI,
    WORLD_MIX,
    build_contact_candidates,
    candidate_after,
    cell_bucket,
    cell_of,
    insert_contact_grid,
    is_candidate,
    next_candidate,
    prepare_contact_particles,
)
from .pairs import (
    CANDIDATE_REACH,
    FACE_REACH,
    accumulated_impulse,
    facing_normal,
    near_pair,
    pair_allowed,
    pair_contact,
    pair_normal,
    projection_term,
    touching_pair,
    warm_impulse,
    within_cone,
)
from .response import find_particle_contacts, resolve_contact_last_pass, resolve_contact_velocities

__all__ = [
    "CANDIDATE_REACH",
    "CELL_WRAP",
    "FACE_REACH",
    "FIBONACCI",
    "WORLD_MIX",
    "accumulated_impulse",
    "build_contact_candidates",
    "candidate_after",
    "cell_bucket",
    "cell_of",
    "facing_normal",
    "find_particle_contacts",
    "insert_contact_grid",
    "is_candidate",
    "near_pair",
    "next_candidate",
    "pair_allowed",
    "pair_contact",
    "pair_normal",
    "prepare_contact_particles",
    "projection_term",
    "resolve_contact_last_pass",
    "resolve_contact_velocities",
    "touching_pair",
    "warm_impulse",
    "within_cone",
]

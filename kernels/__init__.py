"""Warp kernels of softsim-warp, installed as ``softsim_warp.kernels``: one module per physics topic.

Every kernel and ``wp.func`` is defined once, at module level, for both precisions
(:mod:`.precision`); call sites import the topic module and name the kernel they launch
(``wp.launch(contact.collide_planes, ...)``), so "go to definition" finds it and a test can launch
it alone. The topics:

* :mod:`.springs`: the spring force, energy and Jacobian, and the spring-list kernels.
* :mod:`.integration`: the explicit stage update (``stage_values``) and ``integrate_stage``.
* :mod:`.lattice`: springs implicit in a lattice: the per-particle gather, the fused stages, the
  CPU row kernels and the masked lattice of mesh jellies.
* :mod:`.contact`: terrain contact (restitution, friction, moving terrain) with planes, bowls and
  spheres.
* :mod:`.mesh`: mesh terrain (distance, contact, animated meshes) and voxelisation of mesh jellies.
* :mod:`.particle_contact`: contact between jellies and self-contact.
* :mod:`.pins`: held and driven particles, and the rigid motions moving terrain shares.
* :mod:`.implicit`: the implicit Euler solve (Jacobians, CG, contact constraints).
* :mod:`.multigrid`: the implicit solve's multigrid preconditioner.
* :mod:`.metrics`: per-frame reductions (energy, centre of mass, speed, penetration, errors).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

"""The simulation core: model and builder, forces, contact, integrators, terrain geometry.

Imports nothing from ``softsim_warp.io`` or ``softsim_warp.commands``; kernels live in ``softsim_warp.kernels``.
"""

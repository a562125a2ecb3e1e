"""Per-frame metrics summed in a fixed order, for ``--deterministic`` runs (see ``deterministic.py``)."""

from __future__ import annotations

import numpy as np
import warp as wp

from .simulate import MetricsProbe

CHUNK = 256
"""Consecutive particles (springs) summed by one thread of a deterministic metrics reduction."""


def _chunks(owner: np.ndarray, jelly_count: int, chunk: int = CHUNK):
    """Split indices 0..len(owner) into runs of one owner (jelly) of at most ``chunk``; group them by owner.

    Returns:
        ``(start, end, jelly_chunk_start)`` int32 arrays: chunk c covers [start[c], end[c]); the
        chunks of jelly j are jelly_chunk_start[j]:jelly_chunk_start[j + 1], in ascending index order.
    """
    n = owner.shape[0]
    if n == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(jelly_count + 1, np.int32)
    breaks = np.flatnonzero(np.diff(owner)) + 1
    run_start = np.concatenate([[0], breaks])
    run_end = np.concatenate([breaks, [n]])
    starts, ends = [], []
    for a, b in zip(run_start, run_end):
        s = np.arange(a, b, chunk)
        starts.append(s)
        ends.append(np.minimum(s + chunk, b))
    start = np.concatenate(starts)
    end = np.concatenate(ends)
    jelly = owner[start]
    order = np.argsort(jelly, kind="stable")
    start, end, jelly = start[order], end[order], jelly[order]
    jelly_chunk_start = np.searchsorted(jelly, np.arange(jelly_count + 1), side="left")
    return start.astype(np.int32), end.astype(np.int32), jelly_chunk_start.astype(np.int32)


class DeterministicMetricsProbe(MetricsProbe):
    """:class:`~softsim_warp.simulate.MetricsProbe` with fixed-order sums (chunks, then jellies)."""

    def __init__(self, model):
        super().__init__(model)
        dev = model.device
        j = max(len(model.jellies), 1)
        jelly_of = model.particle_jelly.numpy()
        ps, pe, pj = _chunks(jelly_of, j)
        self._p_chunks = [wp.array(a, dtype=wp.int32, device=dev) for a in (ps, pe, pj)]
        n = ps.shape[0]
        self._p_partial = [
            wp.zeros(n, dtype=model.scalar, device=dev),
            wp.zeros(n, dtype=model.scalar, device=dev),
            wp.zeros(n, dtype=model.vec3, device=dev),
            wp.zeros(n, dtype=model.scalar, device=dev),
            wp.zeros(n, dtype=wp.int32, device=dev),
        ]
        spring_owner = jelly_of[model.spring_indices_host[:, 0]] if model.spring_count else np.zeros(0, np.int32)
        ss, se, sj = _chunks(spring_owner, j)
        self._s_chunks = [wp.array(a, dtype=wp.int32, device=dev) for a in (ss, se, sj)]
        self._s_partial = wp.zeros(ss.shape[0], dtype=model.scalar, device=dev)

    def _reduce(self, state):
        m = self.model
        k = m.kernels
        start, end, jelly_start = self._p_chunks
        if start.shape[0]:
            wp.launch(
                k.reduce_particle_chunks,
                dim=start.shape[0],
                inputs=[start, end, m.particle_mass, m.gravity, state.particle_q, state.particle_qd],
                outputs=self._p_partial,
                device=m.device,
            )
        wp.launch(
            k.combine_particle_chunks,
            dim=jelly_start.shape[0] - 1,
            inputs=[jelly_start, *self._p_partial],
            outputs=[self.kinetic, self.gravity_energy, self.moment, self.max_speed, self.nonfinite],
            device=m.device,
        )
        start, end, jelly_start = self._s_chunks
        if start.shape[0]:
            wp.launch(
                k.reduce_spring_chunks,
                dim=start.shape[0],
                inputs=[start, end, m.spring_indices, m.spring_rest_length, m.spring_stiffness, state.particle_q],
                outputs=[self._s_partial],
                device=m.device,
            )
        wp.launch(
            k.combine_spring_chunks,
            dim=jelly_start.shape[0] - 1,
            inputs=[jelly_start, self._s_partial],
            outputs=[self.spring_energy],
            device=m.device,
        )

"""Opt-in timing of the parts of a step (``softsim run --profile``).

A normal run replays captured graphs and never synchronises inside a step, so the time of one part
of a step cannot be read from it. A :class:`StepProfile` brackets each part with a device
synchronise and a host clock: an integrator wraps its parts in ``with self.profile.part(name):``
and the stepper wraps each step in ``with profile.step():``. Parts nest, and each second is charged
to the innermost open part only, so a part's seconds exclude those of the parts inside it and the
parts of a step add up to the step's time; what a step does outside every named part (driven pins,
statistics) is charged to :data:`OTHER`.

Without profiling an integrator holds :data:`NO_PROFILE`, whose contexts do nothing: no
synchronise, no launch, and inside a captured graph nothing at all (Python runs only while
capturing). A profiled step must launch its kernels one by one (a synchronise inside a capture
would record nothing), which is why its times serve to compare the parts, not to measure the speed
of a captured step.
"""

from __future__ import annotations

import contextlib
import time

import warp as wp

# The part a step's time goes to when no named part is open.
OTHER = "other"

_NOTHING = contextlib.nullcontext()


class NoProfile:
    """The profile of an integrator that is not profiled: every context is a shared no-op."""

    active = False

    def part(self, name: str):
        return _NOTHING

    def step(self):
        return _NOTHING

    def reset(self):
        pass


NO_PROFILE = NoProfile()


class StepProfile:
    """Seconds per part of the steps taken on ``device``, each part bracketed by a synchronise.

    Attributes:
        seconds: seconds per part name, in the order the parts were first entered.
        steps: steps timed (``step()`` contexts closed).
        total: seconds of the steps, from the synchronise that opens each to the one that closes
            it; the sum of ``seconds`` when every part was entered inside a step.
    """

    active = True

    def __init__(self, device):
        self.device = wp.get_device(device)
        self.seconds: dict[str, float] = {}
        self.steps = 0
        self.total = 0.0
        self._open: list[str] = []
        self._mark = 0.0

    def reset(self):
        """Forget what was timed so far (e.g. the warm-up step, which includes compiling)."""
        self.seconds = {}
        self.steps = 0
        self.total = 0.0

    def _charge(self):
        # Everything launched so far has finished: the time since the last mark belongs to the
        # innermost open part.
        wp.synchronize_device(self.device)
        now = time.perf_counter()
        if self._open:
            name = self._open[-1]
            self.seconds[name] = self.seconds.get(name, 0.0) + (now - self._mark)
        self._mark = now

    @contextlib.contextmanager
    def part(self, name: str):
        """Charge the time inside this block, less that of the parts nested in it, to ``name``."""
        self._charge()
        self._open.append(name)
        try:
            yield
        finally:
            self._charge()
            self._open.pop()

    @contextlib.contextmanager
    def step(self):
        """One step: its time not inside a named part goes to :data:`OTHER`.

        A step stopped by an exception (an interrupt) adds its time to ``total`` but does not
        count as a step, so the parts still add up to ``total``."""
        start = None
        try:
            with self.part(OTHER):
                start = self._mark
                yield
            self.steps += 1
        finally:
            if start is not None:
                self.total += self._mark - start

    def stats(self) -> dict:
        """The metrics summary's keys: steps timed, their seconds, and seconds per part (:data:`OTHER` last)."""
        parts = {name: t for name, t in self.seconds.items() if name != OTHER}
        if OTHER in self.seconds:
            parts[OTHER] = self.seconds[OTHER]
        return {
            "time_steps": self.steps,
            "time_total_s": self.total,
            "time_parts_s": parts,
        }

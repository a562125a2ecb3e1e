"""Studies: the measurements behind ``softsim bench``, ``accuracy``, ``compare`` and ``stability``.

Library code between ``io`` and ``commands``: each module runs models and returns a JSON-ready
report (with its table and plot), and takes plain values, not parsed command lines. The command
modules parse the flags, call these functions, print and save; tests, ``benchmarks/`` and
``docs/*.py`` import them from here.

* ``bench``: particle-steps per second of the integrators and force paths (timed cases, step
  bytes, copy bandwidth, GPU clocks); ``bench_contact``: the cost of contact between jellies;
  ``bench_newton``: the same jelly stepped by Newton; ``timing``: a step function timed as one
  unit of steps (graph replay or plain launches).
* ``accuracy``: error against a float64 rk4 reference and wall time, per integrator and dt.
* ``compare``: variants of a scene as worlds of one model, side by side in one USD stage.
* ``stability``: the largest stable dt of each integrator, measured by bisection and predicted.
"""

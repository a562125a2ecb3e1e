"""Parameter sweeps: many variants of one scene, batched as worlds, run as Dask tasks, kept as rows.

The pieces, in the order ``softsim sweep`` uses them, one module each:

* :mod:`.plan` -- **planning variants**: ``--vary KEY=...`` axes (lists, linear or log ranges), their
  product or a Latin hypercube (``--samples``), times ``--integrators`` and ``--dts``, each variant a
  validated scene dict; and the **batches** of variants that can share launches, sized by the memory
  each variant needs.
* :mod:`.batch` -- **running a batch on a device** (a Dask task): one model holds the batch's
  variants as worlds and one launch of each kernel steps them all; everything a row records is
  reduced per world on the device, and on the CPU a row equals a single ``softsim run`` bit for bit.
* :mod:`.store` -- **the results store**: each finished task's rows go to a part file at once; the
  results file (Parquet or CSV) is rewritten atomically from the parts; ``--resume`` runs only the
  missing rows.
* :mod:`.cluster` -- **the cluster**: a local ``distributed`` cluster of worker processes (dask-cuda
  with several GPUs) or an existing one at ``--scheduler``; a task whose worker dies runs again
  elsewhere.

The names below are re-exported so that ``from softsim_warp.io.sweep import ...`` reaches each of
them. The row schema is documented in docs/SWEEP.md.
"""

from __future__ import annotations

from .batch import STOP_POLL_SECONDS, TaskStopped, run_batch, stop_check, task_spec
from .cluster import (
    SCHEDULER_EXPECTED,
    SCHEDULER_SCHEMES,
    Cluster,
    Outcome,
    check_scheduler_address,
    dask_setup,
    default_workers,
    run_tasks,
    start_cluster,
)
from .plan import (
    MAX_AXIS_VALUES,
    MAX_BATCH,
    MAX_VARIANTS,
    MEMORY_SHARE,
    Axis,
    SweepVariant,
    batch_size,
    expand_key,
    group_key,
    latin_hypercube,
    make_batches,
    memory_budget,
    parse_axis,
    plan_sweep,
    split_values,
    variant_bytes,
)
# The private name commands/sweep.py's own tasks use (a value's identity).
from .plan import _canonical as _canonical
from .store import (
    CONSOLIDATE_SECONDS,
    KEEP_OUT_MARK,
    REFERENCE_COLUMNS,
    RESULT_COLUMNS,
    RESULT_SUFFIXES,
    STABLE_COLUMNS,
    SWEEP_EXTRA,
    RowStore,
    column_value,
    make_schema,
    read_results,
    require,
)

__all__ = [
    "CONSOLIDATE_SECONDS", "KEEP_OUT_MARK", "MAX_AXIS_VALUES", "MAX_BATCH", "MAX_VARIANTS", "MEMORY_SHARE",
    "REFERENCE_COLUMNS", "RESULT_COLUMNS", "RESULT_SUFFIXES", "SCHEDULER_EXPECTED", "SCHEDULER_SCHEMES",
    "STABLE_COLUMNS", "SWEEP_EXTRA", "Axis", "Cluster", "Outcome", "RowStore", "SweepVariant", "batch_size",
    "check_scheduler_address", "column_value", "dask_setup", "default_workers", "expand_key", "group_key",
    "latin_hypercube", "make_batches", "make_schema", "memory_budget", "parse_axis", "plan_sweep",
    "read_results", "require", "run_batch", "run_tasks", "split_values", "start_cluster", "task_spec",
    "variant_bytes",
]

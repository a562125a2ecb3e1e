"""The results of a sweep: one row per variant, kept as each task finishes.

Each finished task's rows go to a part file at once (written to a temporary and renamed); the
results file (Parquet, or CSV by extension) is rewritten atomically from all parts every few seconds
and at the end (:class:`RowStore`). A sweep stopped by Ctrl-C, a lost worker or a lost scheduler
keeps every finished row, and ``--resume`` runs only the missing ones. A results file that existed
before a sweep (not a ``--resume`` of it) is replaced only by the complete table: until then the rows
go to ``<stem>.partial<ext>`` beside it. The row schema is documented in docs/SWEEP.md.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
from pathlib import Path

from ...core.errors import CommandLineError
from ..outputs import commit, discard, is_stream, kept_partial_path, save_atomic, target_of
from .plan import Axis, SweepVariant, _canonical

# Seconds between rewrites of the results file while tasks finish (parts are written at once).
CONSOLIDATE_SECONDS = 5.0
# In a sweep's parts folder: this sweep may not replace --out until it is complete (RowStore.keep_out).
KEEP_OUT_MARK = "keep-out"
RESULT_SUFFIXES = (".parquet", ".csv")
SWEEP_EXTRA = "pip install 'softsim-warp[sweep]' (dask, distributed, pyarrow)"


def require(module: str):
    """Import an optional dependency of the sweep, or a one-line error saying how to install it."""
    import importlib  # noqa: PLC0415

    try:
        return importlib.import_module(module)
    except ImportError:
        raise CommandLineError("sweep", f"needs the '{module.split('.')[0]}' package: {SWEEP_EXTRA}") from None


RESULT_COLUMNS = [
    ("device", "string"), ("precision", "string"), ("status", "string"),
    ("explosion_time", "float64"), ("explosion_frame", "int64"), ("explosion_reason", "string"), ("error", "string"),
    ("steps", "int64"), ("frames", "int64"), ("sim_time", "float64"), ("particles", "int64"), ("batch_size", "int64"),
    ("wall_seconds", "float64"), ("compile_seconds", "float64"), ("particle_steps_per_second", "float64"),
    ("energy_start", "float64"), ("energy_end", "float64"), ("energy_change", "float64"),
    ("energy_change_relative", "float64"), ("com_x", "float64"), ("com_y", "float64"), ("com_z", "float64"),
    ("max_speed", "float64"), ("max_penetration", "float64"), ("worker", "string"),
]
REFERENCE_COLUMNS = [("ref_status", "string"), ("ref_position_error", "float64"), ("ref_com_error", "float64")]
STABLE_COLUMNS = [
    ("device", "string"), ("precision", "string"), ("status", "string"), ("error", "string"),
    ("stable_dt", "float64"), ("unstable_dt", "float64"), ("bound", "string"), ("probes", "int64"),
    ("duration", "float64"), ("predicted_dt", "float64"),
    ("stable_dt_jelly", "float64"), ("unstable_dt_jelly", "float64"), ("bound_jelly", "string"),
    ("wall_seconds", "float64"), ("worker", "string"),
]


def _arrow_type(pa, values):
    """The Arrow type of a varied key's column: int64, float64, bool or string (JSON text for lists)."""
    if all(isinstance(v, bool) for v in values):
        return pa.bool_()
    if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        return pa.int64()
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return pa.float64()
    return pa.string()


def column_value(value, kind):
    if kind == "string" and not isinstance(value, str):
        return _canonical(value)
    return value


def make_schema(axes: list[Axis], variants: list[SweepVariant], mode: str, meta: dict):
    """The results' Arrow schema: identity, varied keys, integrator and dt, then the mode's columns."""
    pa = require("pyarrow")
    fields = [pa.field("variant_id", pa.string()), pa.field("index", pa.int64())]
    for a in axes:
        if a.key == "simulation.dt":
            continue
        fields.append(pa.field(a.key, _arrow_type(pa, [v.values[a.key] for v in variants] or a.values)))
    fields += [pa.field("integrator", pa.string()), pa.field("dt", pa.float64())]
    if mode == "stable_dt":
        cols = STABLE_COLUMNS
    else:
        cols = RESULT_COLUMNS + (REFERENCE_COLUMNS if mode == "reference" else [])
    fields += [pa.field(name, getattr(pa, kind)()) for name, kind in cols]
    return pa.schema(fields, metadata={"softsim:sweep": json.dumps(meta, sort_keys=True, default=str)})


class RowStore:
    """The results of one sweep on disk: part files as tasks finish, one consolidated file.

    Parts live in the hidden folder ``.<name>.parts`` beside the results file; each is written to a
    temporary and renamed, so a part is whole or absent. :meth:`consolidate` rewrites the results
    file atomically from the rows it had, the parts and nothing else; after a complete sweep the
    parts are removed. Rows are told apart by ``variant_id``; a later row of an id replaces none.

    A file at ``out`` that existed before this sweep (and is not being resumed) is another result:
    it is replaced only by the complete table. Until then (``keep_out``) the consolidated rows go to
    ``<stem>.partial<ext>`` beside it (:func:`~softsim_warp.io.outputs.kept_partial_path`), and the
    parts folder says so (:data:`KEEP_OUT_MARK`), so that ``--resume`` reads that file and the
    parts, leaves ``out`` alone until the table is complete, and then removes the partial file.
    """

    def __init__(self, out, schema, resume=False):
        self.pa = require("pyarrow")
        self.pq = require("pyarrow.parquet")
        self.out = Path(out)
        self.schema = schema
        target = target_of(self.out)
        self.parts = target.with_name(f".{target.name}.parts")
        self.partial = kept_partial_path(self.out)
        self.rows = {}  # variant_id -> row dict
        self._part = 0
        self._last = time.monotonic()
        self._own_partial = False  # the partial file holds this sweep's rows (read or written here)
        if resume:
            self.keep_out = (self.parts / KEEP_OUT_MARK).exists()
            self._load()
        elif self.parts.exists():
            raise CommandLineError("--out", f"the rows of an unfinished sweep are in '{self.parts}': add --resume to "
                                   "finish that sweep, or remove the folder to start again", str(out))
        else:
            self.keep_out = target.exists() and not is_stream(target)

    @property
    def results(self) -> Path:
        """Where the rows are consolidated while the sweep is not complete: ``out``, or its partial file."""
        return self.partial if self.keep_out else self.out

    def _read(self, path):
        if path.suffix == ".csv":
            csv = require("pyarrow.csv")
            types_ = {f.name: f.type for f in self.schema}
            table = csv.read_csv(path, convert_options=csv.ConvertOptions(column_types=types_))
        else:
            table = self.pq.read_table(path)
        return table

    def _load(self):
        sources = []
        if self.results.exists():
            sources.append(self.results)
        if self.parts.exists():
            sources += sorted(self.parts.glob("part-*.parquet"))
        want = set(self.schema.names)
        for path in sources:
            try:
                table = self._read(path)
            except Exception as e:  # noqa: BLE001 - a damaged file is the user's to look at
                raise CommandLineError("--resume", f"cannot read '{path}': {e}", str(path)) from None
            if set(table.column_names) != want:
                missing = sorted(want - set(table.column_names)) or sorted(set(table.column_names) - want)
                raise CommandLineError("--resume", f"'{path}' holds rows of another sweep (columns differ: "
                                       f"{', '.join(missing[:4])}); use another --out or run without --resume",
                                       str(path))
            for row in table.to_pylist():
                self.rows.setdefault(row["variant_id"], row)
            self._own_partial |= path == self.partial
            m = re.match(r"part-(\d+)", path.stem)
            if m:
                self._part = max(self._part, int(m.group(1)) + 1)

    def done_ids(self) -> set:
        return set(self.rows)

    def add(self, rows: list[dict]):
        """Keep ``rows`` (one task's): written to a new part file before this returns."""
        rows = [r for r in rows if r["variant_id"] not in self.rows]
        if not rows:
            return
        self.parts.mkdir(exist_ok=True)
        mark = self.parts / KEEP_OUT_MARK
        if self.keep_out and not mark.exists():  # before the first part: --resume must know
            note = f"'{self.out.name}' predates this sweep: its rows go to '{self.partial.name}' until it is complete"
            mark.write_text(note + "\n")
        table = self._table(rows)
        path = self.parts / f"part-{self._part:06d}.parquet"
        self._part += 1
        tmp = self.parts / f".{path.stem}.partial-{os.getpid()}.parquet"
        try:
            self.pq.write_table(table, tmp)
        except BaseException:
            discard(tmp)
            raise
        commit(tmp, path, "--out")
        for r in rows:
            self.rows[r["variant_id"]] = r

    def _table(self, rows):
        names = self.schema.names
        kinds = {f.name: ("string" if f.type == self.pa.string() else "") for f in self.schema}
        cols = {n: [column_value(r.get(n), kinds[n]) if r.get(n) is not None else None for r in rows] for n in names}
        return self.pa.Table.from_pydict(cols, schema=self.schema)

    def due(self) -> bool:
        return time.monotonic() - self._last >= CONSOLIDATE_SECONDS

    def consolidate(self, final=False):
        """Rewrite the results file from every row kept, in plan order.

        ``final`` (the table is complete) writes ``out`` itself and then removes the parts and the
        partial file of a ``keep_out`` sweep (when it held this sweep's rows); otherwise the rows go
        to :attr:`results`.
        """
        rows = sorted(self.rows.values(), key=lambda r: (r["index"], r["variant_id"]))
        table = self._table(rows)
        path = self.out if final else self.results
        if self.out.suffix == ".csv":
            csv = require("pyarrow.csv")
            save_atomic(path, lambda tmp: csv.write_csv(table, tmp), "--out")
        else:
            save_atomic(path, lambda tmp: self.pq.write_table(table, tmp), "--out")
        self._last = time.monotonic()
        self._own_partial |= path == self.partial
        if final:
            if self._own_partial:
                discard(self.partial)
            if self.parts.exists():
                shutil.rmtree(self.parts, ignore_errors=True)


def read_results(path):
    """The rows of a results file as a list of dicts (Parquet or CSV)."""
    path = Path(path)
    if path.suffix == ".csv":
        return require("pyarrow.csv").read_csv(path).to_pylist()
    return require("pyarrow.parquet").read_table(path).to_pylist()

"""Arrow schemas of the store's tables, and their crash-safe Parquet storage.

Tables live in ``<store>/tables/<name>/`` as many small Parquet files. A writer never appends to an
existing file: it writes one new file per write (temp file + rename on local disks; a single PUT on
object stores), so a crash can leave at most an ignored temp file, never a half-written table.
Readers concatenate all files; ``latest`` de-duplicates by key; ``compact`` merges files.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import fcntl
import io
import uuid
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

POSE = pa.fixed_shape_tensor(pa.float64(), (4, 4))
TIMESTAMP = pa.timestamp("us", tz="UTC")
STR_FLOAT_MAP = pa.map_(pa.string(), pa.float64())

MANIFEST = pa.schema([
    pa.field("source", pa.string(), nullable=False, metadata={"doc": "input image path or URI (key)"}),
    pa.field("scene_id", pa.string(), metadata={"doc": "sha256 of the image bytes"}),
    pa.field("status", pa.string(), nullable=False, metadata={"doc": "pending | running | done | failed"}),
    pa.field("step", pa.string(), metadata={"doc": "last step reached, or the step that failed"}),
    pa.field("error", pa.string(), metadata={"doc": "what went wrong and how to fix it"}),
    pa.field("backend", pa.string(), metadata={"doc": "simulation | onnx"}),
    pa.field("run_id", pa.string()),
    pa.field("updated_at", TIMESTAMP, nullable=False),
    pa.field("seconds", pa.float64(), metadata={"doc": "sum of step execution times"}),
    pa.field("timings", STR_FLOAT_MAP, metadata={"doc": "step group path -> seconds"}),
    pa.field("metrics", STR_FLOAT_MAP),
    pa.field("n_points", pa.int64()),
    pa.field("outputs", pa.string(), metadata={"doc": "exports directory, relative to the store"}),
])

STEPS = pa.schema([
    pa.field("scene_id", pa.string(), nullable=False),
    pa.field("step", pa.string(), nullable=False, metadata={"doc": "group path, e.g. iter_1/lift"}),
    pa.field("event", pa.string(), nullable=False, metadata={"doc": "completed | skipped | failed"}),
    pa.field("key", pa.string()),
    pa.field("exec_id", pa.string()),
    pa.field("run_id", pa.string()),
    pa.field("backend", pa.string()),
    pa.field("at", TIMESTAMP, nullable=False),
    pa.field("seconds", pa.float64()),
    pa.field("error", pa.string()),
])

TRAJECTORIES = pa.schema([
    pa.field("scene_id", pa.string(), nullable=False),
    pa.field("iteration", pa.int32(), nullable=False),
    pa.field("frame", pa.int32(), nullable=False),
    pa.field("c2w", POSE, nullable=False, metadata={"doc": "OpenCV camera-to-world, world frame"}),
    pa.field("fx", pa.float64()), pa.field("fy", pa.float64()),
    pa.field("cx", pa.float64()), pa.field("cy", pa.float64()),
    pa.field("width", pa.int32()), pa.field("height", pa.int32()),
    pa.field("backend", pa.string()),
])

METRICS = pa.schema([
    pa.field("scene_id", pa.string(), nullable=False),
    pa.field("run_id", pa.string()),
    pa.field("name", pa.string(), nullable=False),
    pa.field("value", pa.float64()),
    pa.field("unit", pa.string()),
    pa.field("backend", pa.string()),
    pa.field("created_at", TIMESTAMP, nullable=False),
])

EVALUATIONS = pa.schema([
    pa.field("evaluation_id", pa.string(), nullable=False, metadata={"doc": "one `navcrafter evaluate` run"}),
    pa.field("scene_id", pa.string(), metadata={"doc": "null for a row over all scenes (FID, FVD)"}),
    pa.field("table", pa.string(), nullable=False,
             metadata={"doc": "paper table: I novel-view synthesis (PSNR/SSIM/LPIPS), II FID/FVD, "
                              "III camera pose errors, IV 3D scene reconstruction (3DGS), V planning "
                              "(coverage, noise, F-score, runtime); VI (3DGS ablation) is benchmarks/fitting.py"}),
    pa.field("metric", pa.string(), nullable=False),
    pa.field("value", pa.float64(), metadata={"doc": "null unless status is ok"}),
    pa.field("unit", pa.string()),
    pa.field("status", pa.string(), nullable=False,
             metadata={"doc": "ok | unavailable (e.g. weights missing) | not_built | failed"}),
    pa.field("note", pa.string(), metadata={"doc": "why a value is missing, or how it was measured"}),
    pa.field("backend", pa.string()),
    pa.field("created_at", TIMESTAMP, nullable=False),
])

SCHEMAS: dict[str, pa.Schema] = {"manifest": MANIFEST, "steps": STEPS, "trajectories": TRAJECTORIES,
                                 "metrics": METRICS, "evaluations": EVALUATIONS}


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def to_table(name: str, rows: Sequence[dict[str, Any]]) -> pa.Table:
    """Rows (dicts) to a table of schema ``name``; missing nullable fields become null."""
    schema = SCHEMAS[name]
    unknown = {k for r in rows for k in r} - set(schema.names)
    if unknown:
        raise KeyError(f"table {name!r} has no column(s) {sorted(unknown)}")
    arrays = []
    for f in schema:
        values = [r.get(f.name) for r in rows]
        if f.type == POSE:
            arrays.append(pa.FixedShapeTensorArray.from_numpy_ndarray(
                np.asarray(values, dtype=np.float64).reshape(len(rows), 4, 4)))
        elif f.type == STR_FLOAT_MAP:
            arrays.append(pa.array([None if v is None else [(str(k), float(x)) for k, x in v.items()]
                                    for v in values], type=f.type))
        else:
            arrays.append(pa.array(values, type=f.type))
    return pa.Table.from_arrays(arrays, schema=schema)


class Tables:
    """Parquet tables under ``<root>/tables`` on an fsspec filesystem."""

    def __init__(self, fs, root: str, local: bool) -> None:
        self.fs, self.root, self.local = fs, root.rstrip("/") + "/tables", local

    def _dir(self, name: str) -> str:
        if name not in SCHEMAS:
            raise KeyError(f"unknown table {name!r}; known: {sorted(SCHEMAS)}")
        return f"{self.root}/{name}"

    def write(self, name: str, rows: Sequence[dict[str, Any]] | pa.Table, part: str | None = None) -> str:
        """Write rows as one new Parquet file (``part`` names it; default: time-ordered unique name).

        Writing the same ``part`` again replaces that file atomically (idempotent writers).
        """
        table = rows if isinstance(rows, pa.Table) else to_table(name, rows)
        part = part or f"{utcnow():%Y%m%dT%H%M%S%f}-{uuid.uuid4().hex[:8]}"
        path = f"{self._dir(name)}/{part}.parquet"
        buf = io.BytesIO()
        pq.write_table(table, buf)
        atomic_write(self.fs, path, buf.getvalue(), self.local)
        return path

    def files(self, name: str) -> list[str]:
        d = self._dir(name)
        if not self.fs.exists(d):
            return []
        return sorted(p for p in self.fs.ls(d, detail=False)
                      if p.endswith(".parquet") and not p.rsplit("/", 1)[-1].startswith("."))

    def read(self, name: str, files: Iterable[str] | None = None) -> pa.Table:
        """All rows of a table. A file removed by a concurrent compaction while being read makes the
        read start over: the merged file is always in place before its sources are removed."""
        schema = SCHEMAS[name]
        for _ in range(5):
            parts = []
            try:
                for p in (self.files(name) if files is None else files):
                    with self.fs.open(p, "rb") as fh:
                        parts.append(pq.read_table(fh, schema=schema))
            except FileNotFoundError:
                if files is not None:
                    raise
                continue
            return pa.concat_tables(parts) if parts else schema.empty_table()
        raise RuntimeError(f"table {name!r} kept changing while being read; try again")

    def latest(self, name: str, key: Sequence[str], order: str) -> pa.Table:
        """One row per ``key``: the one with the greatest ``order`` (later files win ties)."""
        t = self.read(name)
        if t.num_rows == 0:
            return t
        t = t.append_column("__row", pa.array(np.arange(t.num_rows)))
        t = t.sort_by([(order, "ascending"), ("__row", "ascending")])
        keys = [tuple(v) for v in zip(*(t.column(k).to_pylist() for k in key))]
        last: dict[tuple, int] = {}
        for i, k in enumerate(keys):
            last[k] = i
        t = t.take(pa.array(sorted(last.values()))).drop_columns(["__row"])
        return t.sort_by([(k, "ascending") for k in key])

    def compact(self, name: str) -> int:
        """Merge all files of a table into one; returns how many files were merged.

        Safe beside concurrent writers and readers: only the files read are removed, after the merged
        file (whose rows are a superset of theirs) is in place. Compactions exclude each other (a lock
        file on local disks), so no row is ever merged twice; on object stores, which have no lock,
        compaction is skipped (0 is returned) and readers simply read more files.
        """
        if not self.local:
            return 0
        lock_dir = f"{self.root}/.locks"
        self.fs.makedirs(lock_dir, exist_ok=True)
        with open(f"{lock_dir}/{name}.lock", "a+b") as lock:
            fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
            files = self.files(name)
            if len(files) < 2:
                return 0
            merged = self.read(name, files)
            self.write(name, merged, part=f"{utcnow():%Y%m%dT%H%M%S%f}-compacted-{uuid.uuid4().hex[:8]}")
            for p in files:
                self.fs.rm(p)
            return len(files)


def atomic_write(fs, path: str, data: bytes, local: bool) -> None:
    """Write a whole file so that readers see the old content or the new, never a part."""
    parent = path.rsplit("/", 1)[0]
    fs.makedirs(parent, exist_ok=True)
    if local:
        tmp = f"{parent}/.tmp-{uuid.uuid4().hex}"
        try:
            with fs.open(tmp, "wb") as fh:
                fh.write(data)
            fs.mv(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):  # e.g. a full disk: leave no partial temp file behind
                fs.rm(tmp)
            raise
    else:  # one PUT is atomic on object stores
        fs.pipe_file(path, data)

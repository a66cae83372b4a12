"""The store: a Zarr v3 hierarchy of scenes plus Parquet tables, on a local directory or any fsspec URL.

Step protocol (what makes runs resumable):

1. ``SceneStore.begin(step, k, key)`` deletes whatever is at the step's group path and creates it
   afresh with ``complete = false``;
2. the step writes its arrays (validated against ``schemas.layout``) and files;
3. ``StepWriter.commit()`` sets ``complete = true`` (plus key, timing, backend) in the group's
   attributes, a single key write, which is atomic on local disks and object stores.

A step whose group is complete with the expected key is skipped; any other state is rewritten.
For fault testing, ``NAVCRAFTER_FAULT_INJECT=<group path>`` makes the process kill itself (SIGKILL)
just before committing that group, e.g. ``iter_1/lift``.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import fsspec
import numpy as np
import zarr
from fsspec.implementations.local import LocalFileSystem

from navcrafter.schemas.layout import COMMON_ATTRS, SCHEMA_VERSION, StepSpec, scene_group
from navcrafter.schemas.tables import Tables, atomic_write, utcnow

FAULT_ENV = "NAVCRAFTER_FAULT_INJECT"


class StoreError(RuntimeError):
    pass


@dataclass(frozen=True)
class StepStatus:
    path: str
    exists: bool
    complete: bool
    attrs: dict[str, Any]

    @property
    def key(self) -> str | None:
        return self.attrs.get("key")


class Store:
    """Root of a navcrafter store. ``uri``: a local path, ``file://...`` or any fsspec URL."""

    def __init__(self, uri: str | os.PathLike, *, create: bool = True) -> None:
        self.uri = str(uri)
        self.fs, root = fsspec.core.url_to_fs(self.uri)
        self.local = isinstance(self.fs, LocalFileSystem)
        self.root = root.rstrip("/") if not self.local else str(Path(root).resolve())
        if self.local:
            zstore = zarr.storage.LocalStore(self.root)
        else:
            zstore = zarr.storage.FsspecStore.from_url(self.uri)
        self._zstore = zstore
        exists = self.fs.exists(f"{self.root}/zarr.json")
        if not exists and not create:
            raise StoreError(f"no navcrafter store at {self.uri}: run `navcrafter explore` to create one")
        if exists:
            group = zarr.open_group(store=zstore, mode="r+")
            version = group.attrs.get("navcrafter_schema_version")
            if version != SCHEMA_VERSION:
                raise StoreError(f"{self.uri} is not a navcrafter store of schema v{SCHEMA_VERSION} "
                                 f"(found {version!r}); use a new store directory")
        else:
            self.fs.makedirs(self.root, exist_ok=True)
            group = zarr.open_group(store=zstore, mode="a")
            group.attrs.update({"navcrafter_schema_version": SCHEMA_VERSION})
        self.group = group
        self.tables = Tables(self.fs, self.root, self.local)

    # -- scenes -----------------------------------------------------------------------------------
    def scene(self, scene_id: str) -> SceneStore:
        return SceneStore(self, scene_id)

    def scene_ids(self) -> list[str]:
        if "scenes" not in self.group:
            return []
        return sorted(self.group["scenes"].group_keys())

    # -- files ------------------------------------------------------------------------------------
    def path(self, rel: str) -> str:
        return f"{self.root}/{rel}"

    def write_bytes(self, rel: str, data: bytes) -> str:
        path = self.path(rel)
        atomic_write(self.fs, path, data, self.local)
        return path

    def read_bytes(self, rel: str) -> bytes:
        return self.fs.cat_file(self.path(rel))

    @contextlib.contextmanager
    def scene_lock(self, scene_id: str) -> Iterator[None]:
        """Exclusive lock on one scene while a step checks and writes it.

        Local stores use ``flock`` on ``locks/<scene_id>.lock``: it works across threads and
        processes on one machine and is released by the kernel when a process dies (even by
        SIGKILL), so a crashed run never leaves a stale lock. Object stores have no such primitive;
        there the lock is a no-op (locking across machines is part of distributed operation).
        """
        if not self.local:
            yield
            return
        path = Path(self.root) / "locks" / f"{scene_id}.lock"
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a+b") as fh:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


class SceneStore:
    """One scene's groups."""

    def __init__(self, store: Store, scene_id: str) -> None:
        self.store, self.scene_id = store, scene_id
        self.prefix = scene_group(scene_id)

    def _open(self, path: str) -> zarr.Group | None:
        try:
            return zarr.open_group(store=self.store._zstore, path=f"{self.prefix}/{path}", mode="r")
        except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError, zarr.errors.NodeTypeValidationError):
            return None

    def status(self, step: StepSpec, k: int | None = None) -> StepStatus:
        path = step.group_path(k)
        g = self._open(path)
        if g is None:
            return StepStatus(path, False, False, {})
        attrs = g.attrs.asdict()
        return StepStatus(path, True, bool(attrs.get("complete")), attrs)

    def require_complete(self, step: StepSpec, k: int | None = None) -> StepStatus:
        st = self.status(step, k)
        if not st.complete:
            raise StoreError(f"scene {self.scene_id[:12]}: step {st.path} has not completed; "
                             f"its outputs cannot be read (rerun the scene to compute it)")
        return st

    def read(self, step: StepSpec, k: int | None, name: str) -> np.ndarray:
        step.array(name)
        self.require_complete(step, k)
        g = self._open(step.group_path(k))
        return g[name][...]

    def read_all(self, step: StepSpec, k: int | None = None) -> dict[str, np.ndarray]:
        self.require_complete(step, k)
        g = self._open(step.group_path(k))
        return {a.name: g[a.name][...] for a in step.arrays if a.name in g}

    def begin(self, step: StepSpec, k: int | None, key: str, backend: str) -> StepWriter:
        path = step.group_path(k)
        full = f"{self.prefix}/{path}"
        root = self.store.group
        if full in root:
            del root[full]
        # a file-only step (export) may have left files without a zarr group
        if self.store.fs.exists(self.store.path(full)):
            self.store.fs.rm(self.store.path(full), recursive=True)
        scene_group_ = root.require_group(self.prefix)
        if scene_group_.attrs.get("scene_id") != self.scene_id:
            scene_group_.attrs.update({"scene_id": self.scene_id})
        g = root.create_group(full)
        exec_id = uuid.uuid4().hex
        g.attrs.update({"step": step.name, "complete": False, "key": key, "exec_id": exec_id,
                        "backend": backend, "started_at": utcnow().isoformat(),
                        "schema_version": SCHEMA_VERSION})
        return StepWriter(self, step, k, g, exec_id)

    def file_rel(self, step: StepSpec, k: int | None, name: str) -> str:
        return f"{self.prefix}/{step.group_path(k)}/{name}"


class StepWriter:
    """Writes one step's group; nothing is trusted until ``commit``."""

    def __init__(self, scene: SceneStore, step: StepSpec, k: int | None, group: zarr.Group, exec_id: str):
        self.scene, self.step, self.k, self.group, self.exec_id = scene, step, k, group, exec_id
        self.dims: dict[str, int] = {}
        self.written: set[str] = set()
        self.files: dict[str, dict[str, Any]] = {}

    @property
    def path(self) -> str:
        return self.step.group_path(self.k)

    def write(self, name: str, data: np.ndarray) -> None:
        spec = self.step.array(name)
        data = np.asarray(data)
        if data.dtype != np.dtype(spec.dtype):
            raise TypeError(f"{self.path}/{name}: dtype {data.dtype}, schema says {spec.dtype}")
        if data.ndim != len(spec.shape):
            raise ValueError(f"{self.path}/{name}: {data.ndim}-D array, schema says shape {spec.shape}")
        for sym, size in zip(spec.shape, data.shape):
            if isinstance(sym, int):
                if sym != size:
                    raise ValueError(f"{self.path}/{name}: shape {data.shape}, schema says {spec.shape}")
            elif self.dims.setdefault(sym, size) != size:
                raise ValueError(f"{self.path}/{name}: dimension {sym}={size} but {self.dims[sym]} "
                                 f"in an earlier array of this step")
        shape, chunks = spec.resolve(self.dims)
        arr = self.group.create_array(name, shape=shape, dtype=spec.dtype, chunks=chunks,
                                      fill_value=0, attributes={"doc": spec.doc})
        if data.size:
            arr[...] = data
        self.written.add(name)

    def write_file(self, name: str, data: bytes) -> str:
        """A plain file inside the step's directory (exports); returns its store-relative path."""
        import hashlib

        rel = self.scene.file_rel(self.step, self.k, name)
        self.scene.store.write_bytes(rel, data)
        self.files[name] = {"path": rel, "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
        return rel

    def commit(self, seconds: float, **attrs: Any) -> dict[str, Any]:
        missing = [a.name for a in self.step.arrays if not a.optional and a.name not in self.written]
        if missing:
            raise StoreError(f"{self.path}: cannot commit, arrays not written: {missing}")
        final = dict(attrs)
        if self.files:
            final["files"] = self.files
        absent = [a for a in self.step.attrs if a not in final and a not in self.group.attrs]
        if absent:
            raise StoreError(f"{self.path}: cannot commit, attributes not set: {absent}")
        final.update({"complete": True, "finished_at": utcnow().isoformat(), "seconds": float(seconds)})
        if os.environ.get(FAULT_ENV) == self.path:
            os.kill(os.getpid(), signal.SIGKILL)  # fault injection: die with the group incomplete
        self.group.attrs.update(final)
        out = self.group.attrs.asdict()
        assert all(a in out for a in COMMON_ATTRS)
        return out

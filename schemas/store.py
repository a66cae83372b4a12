"""The store: a Zarr v3 hierarchy of scenes plus Parquet tables, on a local directory or any fsspec URL.

Step protocol (what makes runs resumable):

1. ``SceneStore.begin(step, k, key)`` deletes whatever is at the step's group path and creates it
   afresh with ``complete = false``;
2. the step writes its arrays (validated against ``schemas.layout``) and files;
3. ``StepWriter.commit()`` sets ``complete = true`` (plus key, timing, backend) in the group's
   attributes, a single write of the group's ``zarr.json`` (``update_attributes``, never
   ``attrs.update``, which zarr writes once per key), atomic on local disks and object stores.

A step whose group is complete with the expected key is skipped; any other state is rewritten.
For fault testing, ``NAVCRAFTER_FAULT_INJECT=<group path>`` makes the process kill itself (SIGKILL)
just before committing that group, e.g. ``iter_1/lift``.

Object stores (S3, MinIO, GCS... through fsspec): see ``Store``. They have no lock, so the scene
lock is a no-op there; what keeps them consistent is the commit order (arrays and files first, the
``complete`` marker last, in one PUT of the group's ``zarr.json``) and a check, just before that
PUT, that the group still belongs to this writer (see ``StepWriter.commit``).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import json
import os
import signal
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import fsspec
import numpy as np
import zarr
from fsspec.implementations.local import LocalFileSystem
from zarr.errors import ContainsGroupError

from navcrafter.schemas.layout import COMMON_ATTRS, SCHEMA_VERSION, StepSpec, scene_group
from navcrafter.schemas.tables import Tables, atomic_write, utcnow

FAULT_ENV = "NAVCRAFTER_FAULT_INJECT"


class StoreError(RuntimeError):
    pass


class StoreUnavailable(StoreError):
    """The store cannot be reached (object-store server down, network outage, timeouts): retried."""


class StoreFull(StoreError):
    """The store's disk or quota is full: not retried (it does not free itself within seconds)."""


DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


@functools.cache
def _unreachable_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean "the store did not answer": builtin connection errors and timeouts, and
    botocore's and aiohttp's own (s3fs raises those as they are; they are not ``OSError``)."""
    types: list[type[BaseException]] = [ConnectionError, TimeoutError]
    with contextlib.suppress(ImportError):
        from botocore.exceptions import ConnectionError as BotoConnectionError
        from botocore.exceptions import HTTPClientError

        types += [BotoConnectionError, HTTPClientError]
    with contextlib.suppress(ImportError):
        from aiohttp import ClientConnectionError

        types.append(ClientConnectionError)
    return tuple(types)


def store_problem(uri: str, exc: BaseException) -> StoreError | None:
    """A clear error (naming the store and the fix) when ``exc``, or what caused it, means the store
    itself is in trouble: full (``StoreFull``) or unreachable (``StoreUnavailable``); else ``None``."""
    seen = 0
    while exc is not None and seen < 5:
        if isinstance(exc, (StoreFull, StoreUnavailable)):
            return exc
        if isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS:
            return StoreFull(f"the store {uri} is full ({exc.strerror or exc}): free space on its disk (or "
                             f"enlarge it / raise the quota), then rerun the same command; completed steps are kept")
        if isinstance(exc, _unreachable_errors()):
            return StoreUnavailable(f"the store {uri} cannot be reached ({type(exc).__name__}: {exc}): check that "
                                    f"its server is up and reachable from here (endpoint, network, credentials), "
                                    f"then rerun the same command; completed steps are kept")
        if isinstance(exc, (ValueError, TypeError, KeyError, StoreError)):
            return None  # bad input or a bug, whatever it was raised while handling
        exc, seen = exc.__cause__ or exc.__context__, seen + 1
    return None


@dataclass(frozen=True)
class StepStatus:
    path: str
    exists: bool
    complete: bool
    attrs: dict[str, Any]

    @property
    def key(self) -> str | None:
        return self.attrs.get("key")


S3_PROTOCOLS = ("s3", "s3a")
# where an S3 endpoint other than AWS (MinIO, Ceph, moto...) is read from, first found wins
S3_ENDPOINT_ENVS = ("FSSPEC_S3_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3", "AWS_ENDPOINT_URL")


def storage_options_for(uri: str, storage_options: dict[str, Any] | None = None) -> dict[str, Any]:
    """fsspec storage options for ``uri``: ``storage_options`` over defaults read from the environment.

    For ``s3://`` URLs the endpoint comes from ``FSSPEC_S3_ENDPOINT_URL``, ``AWS_ENDPOINT_URL_S3`` or
    ``AWS_ENDPOINT_URL`` (read now, not when fsspec was imported), and directory listings are not
    cached (other processes write the same bucket). Credentials are left to botocore, which reads
    ``AWS_ACCESS_KEY_ID`` / ``AWS_SECRET_ACCESS_KEY`` / ``AWS_SESSION_TOKEN`` / ``AWS_PROFILE`` etc.
    """
    opts: dict[str, Any] = {}
    protocol = fsspec.core.split_protocol(uri)[0]
    if protocol in S3_PROTOCOLS:
        opts["use_listings_cache"] = False
        endpoint = next((os.environ[v] for v in S3_ENDPOINT_ENVS if os.environ.get(v)), None)
        if endpoint:
            opts["endpoint_url"] = endpoint
    opts.update(storage_options or {})
    return opts


class Store:
    """Root of a navcrafter store. ``uri``: a local path, ``file://...`` or any fsspec URL.

    On S3 or an S3-compatible server (MinIO, Ceph...), ``uri`` is ``s3://bucket/prefix`` (the bucket
    must exist; s3fs must be installed). Point it at the server the fsspec/AWS way, e.g. for MinIO::

        export AWS_ENDPOINT_URL=http://minio.local:9000      # or FSSPEC_S3_ENDPOINT_URL
        export AWS_ACCESS_KEY_ID=...  AWS_SECRET_ACCESS_KEY=...
        navcrafter explore photos/ --store s3://bucket/stores/run1

    or in Python ``Store("s3://bucket/prefix", storage_options={"endpoint_url": ..., "key": ...,
    "secret": ...})`` (any s3fs argument; explicit options win over the environment). Worker processes
    open the store from its URI alone, so with several processes prefer the environment variables.

    Zarr arrays go through ``zarr.storage.FsspecStore`` (async s3fs); tables and export files are
    written with one PUT each. What object stores do not give: a lock (``scene_lock`` is a no-op,
    so two runs over one S3 store must not work on the same scene at the same time; a commit that
    finds another writer took its group over fails rather than marking mixed outputs complete) and
    table compaction (skipped; readers read every file).
    """

    def __init__(self, uri: str | os.PathLike, *, create: bool = True,
                 storage_options: dict[str, Any] | None = None) -> None:
        self.uri = str(uri)
        self.storage_options = storage_options_for(self.uri, storage_options)
        self.fs, root = fsspec.core.url_to_fs(self.uri, **self.storage_options)
        self.local = isinstance(self.fs, LocalFileSystem)
        self.root = root.rstrip("/") if not self.local else str(Path(root).resolve())
        if self.local:
            zstore = zarr.storage.LocalStore(self.root)
        else:
            zstore = zarr.storage.FsspecStore.from_url(self.uri, storage_options=self.storage_options)
        self._zstore = zstore
        exists = self.fs.exists(f"{self.root}/zarr.json")
        if not exists and not create:
            raise StoreError(f"no navcrafter store at {self.uri}: run `navcrafter explore` to create one")
        if exists:
            group = self._open_root(zstore)
        else:  # the root zarr.json is written once, with its version (another process may be reading)
            self.fs.makedirs(self.root, exist_ok=True)
            try:
                group = zarr.open_group(store=zstore, mode="a", zarr_format=3,
                                        attributes={"navcrafter_schema_version": SCHEMA_VERSION})
            except ContainsGroupError:  # another process created it since the check: open theirs
                group = self._open_root(zstore)
        self.group = group
        self.tables = Tables(self.fs, self.root, self.local)

    # -- scenes -----------------------------------------------------------------------------------
    def _open_root(self, zstore, attempts: int = 20) -> zarr.Group:
        """The existing root group; a root another process is creating this instant (its zarr.json
        not yet whole) is waited for briefly rather than taken for a foreign store."""
        version = None
        for attempt in range(attempts):
            try:
                group = zarr.open_group(store=zstore, mode="r+", zarr_format=3)
                version = group.attrs.get("navcrafter_schema_version")
            except ValueError:  # a zarr.json being written
                version = None
            if version == SCHEMA_VERSION:
                return group
            if version is not None:
                break
            time.sleep(0.05 * (attempt + 1))
        raise StoreError(f"{self.uri} is not a navcrafter store of schema v{SCHEMA_VERSION} "
                         f"(found {version!r}); use a new store directory")

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
        there the lock is a no-op (locking across machines is part of distributed operation): a
        crashed or repeated step is still safe, since a group is only trusted once its ``complete``
        marker, written last, is there, and a rerun rewrites any incomplete group from scratch.
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
            return zarr.open_group(store=self.store._zstore, path=f"{self.prefix}/{path}", mode="r",
                                   zarr_format=3)
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

    def read_rows(self, step: StepSpec, k: int | None, name: str, rows: list[int]) -> np.ndarray:
        """``read(...)[rows]``, reading only the chunks that hold those rows (e.g. a few frames)."""
        step.array(name)
        self.require_complete(step, k)
        return self._open(step.group_path(k))[name].oindex[list(rows)]

    def has(self, step: StepSpec, k: int | None, name: str) -> bool:
        """Whether a complete step wrote the (optional) array ``name``."""
        step.array(name)
        self.require_complete(step, k)
        return name in self._open(step.group_path(k))

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
            scene_group_.update_attributes({"scene_id": self.scene_id})
        g = root.create_group(full)
        exec_id = uuid.uuid4().hex
        g.update_attributes({"step": step.name, "complete": False, "key": key, "exec_id": exec_id,
                        "backend": backend, "started_at": utcnow().isoformat(),
                        "schema_version": SCHEMA_VERSION})
        return StepWriter(self, step, k, g, exec_id)

    def discard(self, step: StepSpec, k: int | None, exec_id: str) -> None:
        """Remove an incomplete group that writer ``exec_id`` began (e.g. to give a full disk back the
        space of a step that failed; a rerun rewrites it from scratch anyway)."""
        st = self.status(step, k)
        if st.exists and not st.complete and st.attrs.get("exec_id") == exec_id:
            self.store.fs.rm(self.store.path(f"{self.prefix}/{st.path}"), recursive=True)

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
        if not self.scene.store.local:
            self._check_still_ours()
        self.group.update_attributes(final)  # the complete marker: one write of the group's zarr.json
        out = self.group.attrs.asdict()
        assert all(a in out for a in COMMON_ATTRS)
        return out

    def _check_still_ours(self) -> None:
        """Without a lock (object stores), another run may have restarted this group meanwhile
        (``begin`` deletes and recreates it). Marking it complete then could certify a mix of two
        writers' arrays, so refuse: the group stays incomplete and a rerun recomputes it."""
        store = self.scene.store
        group_dir = store.path(self.scene.file_rel(self.step, self.k, ""))
        try:  # one GET and one LIST, bypassing zarr (which would open every array)
            on_store = json.loads(store.fs.cat_file(f"{group_dir}zarr.json"))["attributes"].get("exec_id")
            present = {p.rstrip("/").rsplit("/", 1)[-1] for p in store.fs.ls(group_dir, detail=False)}
        except FileNotFoundError:
            on_store, present = None, set()
        missing = sorted(self.written - present)
        if on_store != self.exec_id or missing:
            raise StoreError(f"scene {self.scene.scene_id[:12]}: {self.path} was rewritten by another "
                             f"run (exec_id {on_store!r}, missing arrays {missing}) while this one "
                             f"wrote it; not committed, rerun to recompute it")

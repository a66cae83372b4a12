"""ONNX model directories: export, manifest with checksums, and onnxruntime sessions.

Every exported model directory (synthesizer, geometry, monodepth) has the same shape::

    DIR/manifest.json      what the directory holds (see ``write_manifest``)
    DIR/<graph>.onnx       one file per graph
    DIR/<graph>.onnx.data  external weights (always written, so >2 GB models need no special case)
    DIR/...                other files named in the manifest (e.g. precomputed text embeddings)

The manifest names the model kind and architecture, the model config (enough to rebuild the torch
module), where the weights came from (``random`` or a checkpoint with its sha256), each graph's inputs,
outputs and dynamic axes, and the sha256 of every file. ``load_manifest`` verifies the checksums, so a
truncated copy or a half-finished export fails with a clear error instead of a wrong result.

Precision per execution provider (decided here once, used by every backend):
- CPUExecutionProvider: fp32 (onnxruntime has no bf16 kernels on CPU; fp16 is emulated and slower).
- CUDAExecutionProvider: the graphs are exported in fp32 as well; onnxruntime's CUDA EP runs them with
  TF32 matmuls where the GPU allows. (bf16 has gaps in the CUDA EP's contrib ops, see ../shared/FACTS.md.)
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MANIFEST = "manifest.json"
FORMAT = "navcrafter-onnx"
FORMAT_VERSION = 1
OPSET = 18


class ModelDirError(ValueError):
    """A model directory is missing, incomplete, corrupt or of the wrong kind."""


def config_to_dict(config) -> dict[str, Any]:
    """A model-config dataclass as the JSON a manifest stores (tuples become lists)."""
    import dataclasses

    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(config).items()}


def config_from_dict(cls, data: dict[str, Any]):
    """The inverse of ``config_to_dict`` (lists become tuples); unknown fields are an error."""
    import dataclasses

    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} fields {unknown}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


def sha256_file(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


@dataclass
class GraphInfo:
    """One exported graph: its file, input/output names and which axes are dynamic."""

    file: str
    inputs: list[str]
    outputs: list[str]
    dynamic: dict[str, list[str]] = field(default_factory=dict)  # input name -> axis names ("" = static)
    notes: str = ""


def export_graph(module, args: tuple, path: Path, *, input_names: list[str], output_names: list[str],
                 dynamic_shapes: Any = None, kwargs: dict | None = None, opset: int = OPSET,
                 optimize: bool | None = None) -> GraphInfo:
    """Export ``module(*args, **kwargs)`` with the dynamo exporter to ``path`` (+ ``path.data``).

    ``dynamic_shapes`` follows ``torch.export`` (a tuple/dict of ``{axis: torch.export.Dim}`` per input).
    The weights always go to an external data file next to the graph, so the 2 GB protobuf limit never
    applies. Returns the graph's ``GraphInfo`` (axis names are taken from the exported graph).
    ``optimize`` runs onnxscript's graph optimiser (default: on; ``NAVCRAFTER_ONNX_OPTIMIZE=0`` turns it off).
    Keep it on: without it, onnxruntime 1.32 rejects some exported 3D convolutions (bias shape) of the DiT.
    """
    if optimize is None:
        optimize = os.environ.get("NAVCRAFTER_ONNX_OPTIMIZE", "1") != "0"
    import onnx
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    module.eval()
    with torch.no_grad():
        program = torch.onnx.export(module, args, kwargs=kwargs, dynamo=True, input_names=input_names,
                                    output_names=output_names, dynamic_shapes=dynamic_shapes,
                                    opset_version=opset, verbose=False, optimize=optimize)
    data_name = path.name + ".data"
    for stale in (path, path.parent / data_name):
        if stale.exists():
            stale.unlink()
    program.save(str(path), external_data=True)
    model = onnx.load(str(path), load_external_data=False)
    dynamic: dict[str, list[str]] = {}
    for value in model.graph.input:
        dims = value.type.tensor_type.shape.dim
        dynamic[value.name] = [d.dim_param if d.dim_param else "" for d in dims]
    return GraphInfo(file=path.name, inputs=[v.name for v in model.graph.input],
                     outputs=[v.name for v in model.graph.output], dynamic=dynamic)


def write_manifest(directory: Path, *, kind: str, architecture: str, config: dict, weights: dict,
                   graphs: dict[str, GraphInfo], extra_files: list[str] = (), extra: dict | None = None) -> Path:
    """Write ``directory/manifest.json`` with the sha256 of every graph, data and extra file.

    ``weights`` says where the weights came from: ``{"source": "random", "seed": 0}`` or
    ``{"source": "checkpoint", "path": ..., "sha256": ...}``. Written last (temp file + rename), so a
    directory with a manifest is a finished export.
    """
    import torch

    directory = Path(directory)
    files: dict[str, str] = {}
    for info in graphs.values():
        for name in (info.file, info.file + ".data"):
            if (directory / name).exists():
                files[name] = sha256_file(directory / name)
    for name in extra_files:
        files[name] = sha256_file(directory / name)
    manifest = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "kind": kind, "architecture": architecture,
        "config": config, "weights": weights,
        "graphs": {name: info.__dict__ for name, info in graphs.items()},
        "files": files, "opset": OPSET, "torch": torch.__version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **(extra or {}),
    }
    return _save_manifest(directory, manifest)


def _save_manifest(directory: Path, manifest: dict) -> Path:
    """``directory/manifest.json``, written last and whole (temp file + rename): a directory with a manifest is a
    finished export."""
    tmp = directory / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True))
    os.replace(tmp, directory / MANIFEST)
    return directory / MANIFEST


def checksum_cache_path() -> Path:
    """Where verified checksums are remembered across processes: ``$NAVCRAFTER_CHECKSUM_CACHE`` or
    ``~/.cache/navcrafter/model-checksums.json``."""
    env = os.environ.get("NAVCRAFTER_CHECKSUM_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "navcrafter" / "model-checksums.json"


def _read_checksum_cache() -> dict:
    try:
        data = json.loads(checksum_cache_path().read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def _write_checksum_cache(entries: dict) -> None:
    """Best effort (a read-only home only costs re-hashing next time); temp file + rename."""
    path = checksum_cache_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        merged = {**_read_checksum_cache(), **entries}
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(merged))
        os.replace(tmp, path)
    except OSError:
        pass


def cached_sha256(path: Path, cache: dict, fresh: dict) -> str:
    """sha256 of ``path``, taken from ``cache`` when the file's resolved path, size and mtime (ns) are the
    ones it was hashed at (as git's index trusts them); new digests are added to ``fresh``."""
    st = path.stat()
    key = str(path.resolve())
    hit = cache.get(key)
    if isinstance(hit, list) and len(hit) == 3 and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
        return hit[2]
    digest = sha256_file(path)
    fresh[key] = [st.st_size, st.st_mtime_ns, digest]
    return digest


def external_data_files(graph_path: Path) -> set[str]:
    """The external-data locations an ONNX graph refers to (read without loading the weights)."""
    import onnx

    model = onnx.load(str(graph_path), load_external_data=False)
    out: set[str] = set()

    def visit(graph) -> None:
        for t in graph.initializer:
            if t.data_location == onnx.TensorProto.EXTERNAL:
                out.update(e.value for e in t.external_data if e.key == "location")
        for node in graph.node:
            for a in node.attribute:
                if a.type == onnx.AttributeProto.GRAPH:
                    visit(a.g)
                elif a.type == onnx.AttributeProto.GRAPHS:
                    for g in a.graphs:
                        visit(g)

    visit(model.graph)
    return out


def load_manifest(directory: Path, kind: str, *, verify: bool = True) -> dict:
    """Read and check a model directory's manifest (kind, format, every file present and its sha256, and
    every graph's external data inside the directory and named in the manifest).

    Checksums already verified for a file at the same path, size and modification time (in this or an earlier
    process; ``checksum_cache_path()``) are not recomputed, so a multi-GB model is hashed once, not at every
    worker start. A file rewritten in place with the same size and mtime would escape that check, as it
    escapes git's."""
    directory = Path(directory)
    path = directory / MANIFEST
    if not path.is_file():
        raise ModelDirError(f"{directory} is not an exported {kind} model directory (no {MANIFEST}); "
                            f"create one with `navcrafter models export-{kind}`")
    manifest = json.loads(path.read_text())
    if manifest.get("format") != FORMAT or manifest.get("format_version") != FORMAT_VERSION:
        raise ModelDirError(f"{path}: not a {FORMAT} v{FORMAT_VERSION} manifest; re-export the model")
    if manifest.get("kind") != kind:
        raise ModelDirError(f"{path}: holds a {manifest.get('kind')!r} model, expected {kind!r}")
    root = directory.resolve()
    for name in manifest["files"]:
        f = directory / name
        if not f.resolve().is_relative_to(root):
            raise ModelDirError(f"{path}: file {name!r} lies outside {directory}; refusing to load it")
        if not f.is_file():
            raise ModelDirError(f"{directory}: file {name} named in the manifest is missing; re-export the model")
    if not verify:
        return manifest
    for info in manifest.get("graphs", {}).values():
        for loc in external_data_files(directory / info["file"]):
            target = (directory / info["file"]).parent / loc
            if not target.resolve().is_relative_to(root) or Path(loc).is_absolute():
                raise ModelDirError(f"{directory / info['file']}: external data {loc!r} lies outside {directory}; "
                                    "refusing to load it (re-export the model)")
            if loc not in manifest["files"]:
                raise ModelDirError(f"{directory / info['file']}: external data {loc!r} is not covered by the "
                                    "manifest's checksums; re-export the model")
    cache, fresh = _read_checksum_cache(), {}
    try:
        for name, digest in manifest["files"].items():
            if cached_sha256(directory / name, cache, fresh) != digest:
                fresh.pop(str((directory / name).resolve()), None)  # never remember a mismatch
                raise ModelDirError(f"{directory}: checksum of {name} does not match the manifest (corrupt or "
                                    f"partial copy); re-export or copy the directory again")
    finally:
        if fresh:
            _write_checksum_cache(fresh)
    return manifest


def is_random_weights(manifest: dict) -> bool:
    return manifest.get("weights", {}).get("source") == "random"


def default_providers() -> list[str]:
    """CUDA first when onnxruntime has it, else CPU."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]


def create_session(path: Path, providers: list[str] | None = None, threads: int | None = None):
    """An ``onnxruntime.InferenceSession`` for one graph file."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    if threads:
        options.intra_op_num_threads = threads
    options.log_severity_level = 3
    return ort.InferenceSession(str(path), sess_options=options, providers=providers or default_providers())


class GraphRunner:
    """Sessions for the graphs of one model directory, created on first use."""

    def __init__(self, directory: Path, manifest: dict, providers: list[str] | None = None) -> None:
        self.directory = Path(directory)
        self.manifest = manifest
        self.providers = providers or default_providers()
        self._sessions: dict[str, Any] = {}

    def session(self, graph: str):
        if graph not in self._sessions:
            info = self.manifest["graphs"].get(graph)
            if info is None:
                raise ModelDirError(f"{self.directory}: no graph {graph!r} in the manifest "
                                    f"(has {sorted(self.manifest['graphs'])}); re-export the model")
            self._sessions[graph] = create_session(self.directory / info["file"], self.providers)
        return self._sessions[graph]

    def release(self, keep: str | None = None) -> list[str]:
        """Drop every session but ``keep``'s (their weights leave the device once no run holds them); the next
        ``session`` call creates one again. Returns the graphs released."""
        gone = [g for g in self._sessions if g != keep]
        for g in gone:
            del self._sessions[g]
        return gone

    def run(self, graph: str, feeds: dict[str, Any]) -> dict[str, Any]:
        sess = self.session(graph)
        names = [o.name for o in sess.get_outputs()]
        return dict(zip(names, sess.run(names, feeds)))


# --------------------------------------------------------------------------------------------------
# fp16 graphs for the CUDA execution provider
# --------------------------------------------------------------------------------------------------
#: Operators an fp16 graph keeps in fp32: the normalisations (LayerNorm / RMSNorm, whether exported as one operator or
#: decomposed into a mean of squares and its root), on top of onnxruntime's own list of operators without fp16 kernels.
FP32_OPS = ("LayerNormalization", "SimplifiedLayerNormalization", "RMSNormalization", "ReduceMean", "Pow", "Sqrt",
            "Reciprocal")


def convert_graph_fp16(src: Path, dst: Path) -> GraphInfo:
    """Write an fp16 copy of graph ``src`` to ``dst`` (+ ``dst.data``): weights and activations in fp16, the
    normalisations (``FP32_OPS``) in fp32, inputs and outputs kept fp32 (casts inside), so callers feed it as before.
    onnxruntime's ``transformers.float16`` converter does the rewrite; on the CPU, onnxruntime runs the fp16 nodes
    it has no kernel for through inserted casts (slow, but the same graph), on CUDA in fp16."""
    import onnx
    from onnxruntime.transformers.float16 import DEFAULT_OP_BLOCK_LIST, convert_float_to_float16

    src, dst = Path(src), Path(dst)
    # onnx's shape inference serialises the model: impossible past protobuf's 2 GB (so is asking its size)
    size = src.stat().st_size + sum((src.parent / loc).stat().st_size for loc in external_data_files(src))
    big = size > 2**31 - 2**26
    model = onnx.load(str(src))  # with its external data
    half = convert_float_to_float16(model, keep_io_types=True, disable_shape_infer=big,
                                    op_block_list=sorted(set(DEFAULT_OP_BLOCK_LIST) | set(FP32_OPS)))
    data_name = dst.name + ".data"
    for stale in (dst, dst.parent / data_name):
        stale.unlink(missing_ok=True)
    onnx.save_model(half, str(dst), save_as_external_data=True, all_tensors_to_one_file=True, location=data_name)
    saved = onnx.load(str(dst), load_external_data=False)
    dynamic = {v.name: [d.dim_param if d.dim_param else "" for d in v.type.tensor_type.shape.dim]
               for v in saved.graph.input}
    return GraphInfo(file=dst.name, inputs=[v.name for v in saved.graph.input],
                     outputs=[v.name for v in saved.graph.output], dynamic=dynamic)


def convert_model_dir_fp16(directory: Path, graphs: Sequence[str] = ("dit",)) -> dict:
    """Convert ``graphs`` of an exported model directory to fp16 in place (``<name>.fp16.onnx`` replaces the fp32
    graph and its data, which are removed) and rewrite its manifest: the graph's new file, ``precision`` per graph
    (``"fp32"`` unless converted) and every checksum. Converting a graph that is already fp16 is refused."""
    directory = Path(directory)
    path = directory / MANIFEST
    if not path.is_file():
        raise ModelDirError(f"{directory} is not an exported model directory (no {MANIFEST})")
    manifest = json.loads(path.read_text())
    precision = dict(manifest.get("precision") or {name: "fp32" for name in manifest["graphs"]})
    unknown = [g for g in graphs if g not in manifest["graphs"]]
    if unknown:
        raise ModelDirError(f"{directory}: no graph {unknown} (has {sorted(manifest['graphs'])})")
    done = [g for g in graphs if precision.get(g) == "fp16"]
    if done:
        raise ModelDirError(f"{directory}: graph(s) {done} are fp16 already")
    for g in graphs:
        old = manifest["graphs"][g]["file"]
        info = convert_graph_fp16(directory / old, directory / (Path(old).stem + ".fp16.onnx"))
        for name in (old, old + ".data"):
            (directory / name).unlink(missing_ok=True)
            manifest["files"].pop(name, None)
        manifest["graphs"][g] = {**manifest["graphs"][g], "file": info.file}
        for name in (info.file, info.file + ".data"):
            manifest["files"][name] = sha256_file(directory / name)
        precision[g] = "fp16"
    manifest["precision"] = {name: precision.get(name, "fp32") for name in manifest["graphs"]}
    _save_manifest(directory, manifest)
    return manifest

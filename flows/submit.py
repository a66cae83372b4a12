"""Submitting collections to a Prefect deployment, so that workers (anywhere) explore them.

* ``deploy_local(work_pool)`` creates (or updates) the ``explore-collection/<name>`` deployment from
  this checkout on a *process* work pool: no image is built; a worker on a machine where navcrafter
  is installed and this folder exists runs the flow from it. ``deploy_local(gpu_pool,
  entrypoint=SCENE_ENTRYPOINT)`` does the same for ``explore-scene/<name>``, to which collection runs
  given ``scene_deployment`` dispatch their scenes.
* ``submit_collection(photos, store, config, ...)`` creates flow runs on such a deployment with
  ``run_deployment(..., timeout=0)`` (it returns at once) and gives back their ids: one run for a
  folder or an object-store prefix (``s3://bucket/photos/``), or one run per image (``per_image``; a
  list file is always submitted per image).

Each run is an ordinary ``explore_collection`` run over the shared store: completed steps are
skipped, so a run that was killed (its flow run is then left RUNNING or CRASHED) is finished by
submitting the same collection again.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from navcrafter.flows.dispatch import DispatchError, check_scene_deployment
from navcrafter.schemas.config import RunConfig
from navcrafter.tasks import ingest

REPO_ROOT = Path(__file__).resolve().parent.parent
ENTRYPOINT = "flows/explore.py:explore_collection"
FLOW_NAME = "explore-collection"
SCENE_ENTRYPOINT = "flows/explore.py:explore_scene"
SCENE_FLOW_NAME = "explore-scene"
DEFAULT_DEPLOYMENT_NAME = "default"
DEFAULT_DEPLOYMENT = f"{FLOW_NAME}/{DEFAULT_DEPLOYMENT_NAME}"
LIST_SUFFIXES = (".txt", ".lst", ".list")


class SubmitError(RuntimeError):
    """A problem the user can fix (no server, no deployment, bad collection); the message says how."""


@dataclass
class Submitted:
    deployment: str
    flow_run_ids: list[str]
    photos: list[str]  # what each run was given (same order as flow_run_ids)
    names: list[str] = field(default_factory=list)


def api_url() -> str | None:
    from prefect.settings import get_current_settings

    return get_current_settings().api.url


def ui_url() -> str | None:
    """The dashboard: PREFECT_UI_URL, else the API URL without its ``/api``."""
    from prefect.settings import get_current_settings

    settings = get_current_settings()
    url = settings.ui_url or settings.api.url
    if not url:
        return None
    url = url.rstrip("/")
    return url[: -len("/api")] if url.endswith("/api") else url


def require_server() -> str:
    url = api_url()
    if not url:
        raise SubmitError(
            "submit needs a running Prefect server (PREFECT_API_URL is not set). Start one with "
            "`prefect server start`, then `export PREFECT_API_URL=http://127.0.0.1:4200/api` "
            "(or `prefect config set PREFECT_API_URL=...`), and run workers with `prefect worker start --pool POOL`.")
    return url


def _is_url(s: str) -> bool:
    return "://" in s


def absolute(location: str) -> str:
    """Workers run elsewhere (another working directory): local paths must be absolute."""
    return location if _is_url(location) else str(Path(location).expanduser().resolve())


def is_list_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in LIST_SUFFIXES


def read_list_file(path: Path) -> list[str]:
    """One path per line; blank lines and ``#`` comments skipped; relative paths are relative to the
    list file's folder. Every listed local file must exist (nothing is submitted otherwise)."""
    entries = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        entries.append(line if _is_url(line) else str((path.parent / Path(line).expanduser()).resolve()))
    if not entries:
        raise SubmitError(f"the list file {path} names no images (one path per line)")
    missing = [e for e in entries if not _is_url(e) and not Path(e).exists()]
    if missing:
        raise SubmitError(f"the list file {path} names {len(missing)} missing file(s): "
                          + ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else ""))
    return entries


def collection_items(photos: str | Path, per_image: bool) -> list[str]:
    """What each flow run is given: the folder itself, or each of its images (a list file: its images);
    an fsspec URL (``s3://bucket/photos/``): the prefix itself, or each object under it."""

    if _is_url(str(photos)):
        try:
            items = ingest.list_collection(str(photos))
        except ingest.CollectionError as exc:
            raise SubmitError(str(exc)) from None
        if not items:
            raise SubmitError(f"the collection {photos} holds no files (only hidden ones)")
        return items if per_image else [str(photos)]
    p = Path(photos).expanduser()
    if not p.exists():
        raise SubmitError(f"the collection {p} does not exist; pass a folder of images, one image or a list "
                          f"file ({', '.join(LIST_SUFFIXES)}: one path per line)")
    if is_list_file(p):
        return read_list_file(p)
    if p.is_file() or not per_image:
        return [str(p.resolve())]
    items = ingest.list_collection(p)
    if not items:
        raise SubmitError(f"the collection {p} holds no files")
    return items


def deploy_local(work_pool: str, name: str = DEFAULT_DEPLOYMENT_NAME, source: str | Path = REPO_ROOT,
                 tags: Iterable[str] = (), entrypoint: str = ENTRYPOINT) -> str:
    """Create or update ``explore-collection/<name>`` (or the flow of ``entrypoint``, e.g.
    ``SCENE_ENTRYPOINT``: ``explore-scene/<name>``) on a process work pool, running the flow from
    ``source`` (this checkout, by default) without building an image. Returns the deployment's id."""
    from prefect import flow

    require_server()
    remote = flow.from_source(source=str(source), entrypoint=entrypoint)
    deployment_id = remote.deploy(name=name, work_pool_name=work_pool, build=False, push=False,
                                  tags=list(tags), print_next_steps=False, ignore_warnings=True)
    return str(deployment_id)


def submit_collection(photos: str | Path, store: str, config: RunConfig, deployment: str = DEFAULT_DEPLOYMENT,
                      per_image: bool = False, tags: Iterable[str] = (),
                      job_variables: dict | None = None, scene_deployment: str | None = None) -> Submitted:
    """Create flow runs of ``deployment`` for a collection and return at once (``timeout=0``).

    ``photos``: a folder or object-store prefix (one run, or one per image with ``per_image``), one
    image, or a list file (always one run per listed image). ``store`` and local photo paths are made
    absolute, since the worker's working directory is not ours. ``scene_deployment``: the runs start
    each scene as a flow run of it (else the deployment's default: in-process subflows, unless set).
    """
    from prefect.deployments import run_deployment
    from prefect.exceptions import ObjectNotFound


    require_server()
    items = collection_items(photos, per_image)
    store = absolute(store)
    params_config = config.model_dump(mode="json")
    extra = {}
    if scene_deployment:
        try:
            check_scene_deployment(scene_deployment)
        except DispatchError as exc:
            raise SubmitError(str(exc)) from None
        extra["scene_deployment"] = scene_deployment
    tag_list = ["navcrafter", *[t for t in tags if t != "navcrafter"]]
    ids: list[str] = []
    names: list[str] = []
    for item in items:
        try:
            run = run_deployment(deployment, parameters={"photos": item, "store": store, "config": params_config,
                                                         **extra},
                                 timeout=0, tags=tag_list, as_subflow=False, job_variables=job_variables)
        except ObjectNotFound:
            raise SubmitError(
                f"no deployment {deployment!r} on the Prefect server at {api_url()}. Create it from this "
                f"checkout with `navcrafter submit ... --work-pool POOL` (it deploys {ENTRYPOINT} to POOL, "
                f"a process work pool made by `prefect work-pool create --type process POOL`), or with "
                f"`prefect deploy {ENTRYPOINT} --name {deployment.split('/')[-1]} --pool POOL`.") from None
        ids.append(str(run.id))
        names.append(run.name)
    return Submitted(deployment, ids, items, names)

"""Static checks of ``deploy/``: the Prefect project file, the worker Dockerfiles, the compose stack and
the Kubernetes base job templates. Nothing is built or started; the flows are only loaded."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path
from urllib.parse import urlparse

import prefect
import pytest
import yaml
from prefect.cli.deploy._models import ConcurrencyLimitSpec, DeploymentConfig, PrefectYamlModel
from prefect.utilities.schema_tools import validate as validate_schema
from prefect.utilities.templating import apply_values, find_placeholders

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
PREFECT_YAML = DEPLOY / "prefect.yaml"
COMPOSE = DEPLOY / "compose.yaml"
DOCKERFILES = {"cpu": DEPLOY / "docker" / "Dockerfile.cpu", "gpu": DEPLOY / "docker" / "Dockerfile.cuda"}
K8S_TEMPLATES = {"cpu": DEPLOY / "k8s" / "cpu-job-template.json", "gpu": DEPLOY / "k8s" / "gpu-job-template.json"}
POOLS = {"cpu": "navcrafter-cpu", "gpu": "navcrafter-gpu"}
APP_DIR = "/opt/navcrafter"  # where the images hold the source tree (the pull step's working directory)
EXPECTED = {  # deployment -> (entrypoint, pool kind)
    "explore-collection": ("flows/explore.py:explore_collection", "cpu"),
    "explore-scene": ("flows/explore.py:explore_scene", "gpu"),
    "evaluate-store": ("flows/evaluate.py:evaluate_store", "cpu"),
    "train-camera": ("flows/train_camera.py:train_camera", "gpu"),
}


def _yaml(path: Path):
    return yaml.safe_load(path.read_text())


@pytest.fixture(scope="module")
def project() -> dict:
    return _yaml(PREFECT_YAML)


@pytest.fixture(scope="module")
def deployments(project) -> dict[str, dict]:
    return {d["name"]: d for d in project["deployments"]}


@pytest.fixture(scope="module")
def compose() -> dict:
    return _yaml(COMPOSE)


# --------------------------------------------------------------------------------------------------
# Every file parses
# --------------------------------------------------------------------------------------------------
def test_every_yaml_and_json_file_parses():
    files = sorted(p for p in DEPLOY.rglob("*") if p.suffix in {".yaml", ".yml", ".json"})
    assert {PREFECT_YAML, COMPOSE, *K8S_TEMPLATES.values()} <= set(files)
    for path in files:
        data = json.loads(path.read_text()) if path.suffix == ".json" else _yaml(path)
        assert isinstance(data, dict) and data, f"{path} is empty or not a mapping"


# --------------------------------------------------------------------------------------------------
# prefect.yaml
# --------------------------------------------------------------------------------------------------
def test_prefect_yaml_schema(project, deployments):
    model = PrefectYamlModel.model_validate(project)  # what `prefect deploy` does with the file
    assert project["prefect-version"] == prefect.__version__
    # the models ignore unknown keys: catch misspelt ones here
    top = {f.alias or n for n, f in PrefectYamlModel.model_fields.items()} | {"definitions"}
    assert set(project) <= top, f"unknown top-level keys {set(project) - top}"
    known = set(DeploymentConfig.model_fields)
    for d in project["deployments"]:
        assert set(d) <= known, f"{d['name']}: unknown keys {set(d) - known}"
        assert set(d["work_pool"]) <= {"name", "work_queue_name", "job_variables"}
        assert d.get("tags") and d.get("description")
        assert d.get("enforce_parameter_schema") is True
        limit = d.get("concurrency_limit")
        assert limit is not None, f"{d['name']}: no concurrency limit"
        if isinstance(limit, dict):
            assert set(limit) <= set(ConcurrencyLimitSpec.model_fields), f"{d['name']}: {limit}"
            assert limit.get("limit", 0) >= 1 and limit.get("collision_strategy") in {None, "ENQUEUE", "CANCEL_NEW"}
    assert set(deployments) == set(EXPECTED)
    assert [d.name for d in model.deployments] == [d["name"] for d in project["deployments"]]
    for name, (entrypoint, kind) in EXPECTED.items():
        assert deployments[name]["entrypoint"] == entrypoint
        assert deployments[name]["work_pool"]["name"] == POOLS[kind]


def test_pull_step_sets_the_image_source_directory(project):
    assert not project.get("build") and not project.get("push")
    assert project["pull"] == [{"prefect.deployments.steps.set_working_directory": {"directory": APP_DIR}}]
    for d in project["deployments"]:
        assert "pull" not in d, "a per-deployment pull would replace the working-directory step"


@pytest.fixture(scope="module")
def loaded_flows(deployments, tmp_path_factory) -> dict:
    """Each deployment's flow, loaded as a worker does: the entrypoint resolved from the repo root."""
    import os

    from prefect.flows import load_flow_from_entrypoint

    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        return {name: load_flow_from_entrypoint(d["entrypoint"]) for name, d in deployments.items()}
    finally:
        os.chdir(cwd)


def test_entrypoints_load_as_flows(deployments, loaded_flows):
    for name, d in deployments.items():
        path, func = d["entrypoint"].split(":")
        assert (ROOT / path).is_file(), f"{name}: {path} does not exist"
        flow = loaded_flows[name]
        assert isinstance(flow, prefect.Flow), f"{name}: {d['entrypoint']} is not a flow"
        assert flow.fn.__name__ == func
        if "flow_name" in d:
            assert d["flow_name"] == flow.name


def test_deployment_parameters_fit_the_flow_signatures(deployments, loaded_flows):
    for name, d in deployments.items():
        flow = loaded_flows[name]
        params = d.get("parameters", {})
        accepted = set(flow.parameters.properties)
        assert set(params) <= accepted, f"{name}: {set(params) - accepted} are not parameters of {flow.name}"
        # what the server checks (enforce_parameter_schema): the defaults against the JSON schema
        validate_schema(params, flow.parameters.model_dump_for_openapi(), raise_on_error=True, ignore_required=True)
        # what the flow run does: pydantic validation, with placeholders for what must come at run time
        missing = {p: "x" * 64 for p in flow.parameters.required if p not in params}
        assert set(missing) <= {"scene_id", "run_id"}, f"{name}: required {set(missing)} have no default"
        validated = flow.validate_parameters({**params, **missing})
        if "config" in params and name == "train-camera":
            from navcrafter.schemas.training import CameraTrainingConfig

            assert isinstance(validated["config"], CameraTrainingConfig)
            assert validated["config"].data.sources and validated["config"].base
        elif "config" in params:
            from navcrafter.schemas.config import RunConfig

            assert isinstance(validated["config"], RunConfig)
            assert validated["config"].backend == params["config"]["backend"]


def test_collections_dispatch_their_scenes_to_the_gpu_deployment(deployments, loaded_flows):
    """explore-collection (CPU pool) starts each scene as a flow run of explore-scene (GPU pool), with
    parameters that the scene flow accepts."""
    from navcrafter.flows.dispatch import scene_parameters
    from navcrafter.schemas.config import RunConfig

    target = deployments["explore-collection"]["parameters"]["scene_deployment"]
    flow_name, _, name = target.partition("/")
    assert flow_name == loaded_flows["explore-scene"].name == "explore-scene" and name in deployments
    assert deployments[name]["entrypoint"] == EXPECTED["explore-scene"][0]
    assert deployments[name]["work_pool"]["name"] == POOLS["gpu"]
    assert deployments["explore-collection"]["work_pool"]["name"] == POOLS["cpu"]
    config = RunConfig.model_validate(deployments["explore-collection"]["parameters"]["config"])
    params = scene_parameters("s3://navcrafter/store", "a" * 64, config, "run", ["/data/photos/a.png"])
    scene_flow = loaded_flows["explore-scene"]
    validate_schema(params, scene_flow.parameters.model_dump_for_openapi(), raise_on_error=True)
    validated = scene_flow.validate_parameters(params)
    assert validated["config"] == config and validated["sources"] == ["/data/photos/a.png"]


def test_store_parameter_is_the_compose_bucket(deployments, compose):
    init = compose["services"]["minio-init"]
    script = " ".join(init["command"]) if isinstance(init["command"], list) else init["command"]
    buckets = set(re.findall(r"mc mb (?:--ignore-existing )?\w+/([\w.-]+)", script))
    for name, d in deployments.items():
        if "store" not in d["parameters"]:  # train-camera: a run folder on the GPU node, no store
            continue
        store = urlparse(d["parameters"]["store"])
        assert store.scheme == "s3" and store.netloc in buckets, f"{name}: store bucket is not created"


# --------------------------------------------------------------------------------------------------
# Dockerfiles
# --------------------------------------------------------------------------------------------------
def _instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with line continuations joined and comments dropped."""
    out, buf = [], ""
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if not buf and (not stripped or stripped.startswith("#")):
            continue
        if stripped.startswith("#"):
            continue
        buf += " " + stripped.rstrip("\\").strip() if buf else stripped.rstrip("\\").strip()
        if not stripped.endswith("\\"):
            word, _, rest = buf.partition(" ")
            out.append((word.upper(), rest.strip()))
            buf = ""
    return out


def _stages(path: Path) -> list[dict]:
    """Stages with their resolved base image (ARG defaults before the first FROM substituted)."""
    args, stages = {}, []
    for ins, rest in _instructions(path):
        if ins == "ARG" and not stages and "=" in rest:
            k, v = rest.split("=", 1)
            args[k] = v
        elif ins == "FROM":
            parts = rest.split()
            parts = [p for p in parts if not p.startswith("--")]
            image = re.sub(r"\$\{(\w+)\}|\$(\w+)", lambda m: args[m.group(1) or m.group(2)], parts[0])
            name = parts[2] if len(parts) >= 3 and parts[1].upper() == "AS" else None
            stages.append({"image": image, "name": name, "ins": []})
        elif stages:
            stages[-1]["ins"].append((ins, rest))
    return stages


def _exec_form(rest: str) -> list[str]:
    return json.loads(rest) if rest.startswith("[") else shlex.split(rest)


@pytest.mark.parametrize("kind", sorted(DOCKERFILES))
def test_dockerfile(kind, deployments):
    path = DOCKERFILES[kind]
    stages = _stages(path)
    names = {s["name"] for s in stages if s["name"]}
    assert len(stages) >= 2 and len(names) >= 2, "not multi-stage"
    for s in stages:
        image = s["image"]
        if image in names:
            continue
        repo, _, tag = image.rpartition(":") if ":" in image.split("/")[-1] else (image, "", "")
        assert tag and tag != "latest" and "@" not in repo, f"{path.name}: {image} is not pinned by a version tag"
    if kind == "cpu":
        assert all(s["image"] == "python:3.11-slim-bookworm" for s in stages)
    else:
        assert any(s["image"].startswith("nvidia/cuda:") and "runtime" in s["image"] for s in stages)
    runtime = stages[-1]
    ins = runtime["ins"]
    text = path.read_text()
    # non-root user in the final stage
    users = [rest for i, rest in ins if i == "USER"]
    assert users and users[-1].split(":")[0] not in {"root", "0"}
    # the constraints are used, torch is pinned to the constraints' version, open3d's libusb is there
    constraints = {ln.split("==")[0].lower(): ln.split("==")[1] for ln in
                   (DEPLOY / "constraints.txt").read_text().splitlines() if "==" in ln and not ln.startswith("#")}
    assert "-c deploy/constraints.txt" in text
    assert f"torch=={constraints['torch']}" in text
    if kind == "cpu":
        assert "download.pytorch.org/whl/cpu" in text
    else:
        assert "whl/cpu" not in text and "whl/cu" in text
    assert any(i == "RUN" and "libusb-1.0-0" in rest for i, rest in ins), "runtime stage lacks libusb-1.0-0"
    assert re.search(r"PREFECT_SERVER_ANALYTICS_ENABLED=false", text)
    assert any(i == "HEALTHCHECK" for i, _ in ins)
    # every COPY from the build context exists in the repository
    for stage in stages:
        for i, rest in stage["ins"]:
            if i != "COPY" or "--from=" in rest:
                continue
            srcs = [p for p in _exec_form(rest) if not p.startswith("--")][:-1]
            for src in srcs:
                assert (ROOT / src).exists(), f"{path.name}: COPY source {src} does not exist"
    # the source tree lands where the pull step looks for it
    assert ("WORKDIR", APP_DIR) in ins
    for d in deployments.values():
        assert any(i == "COPY" and d["entrypoint"].split("/")[0] in rest for i, rest in ins)
    # the command starts a worker for this kind's pool, and that pool is the deployments' one
    cmd = _exec_form([rest for i, rest in ins if i == "CMD"][-1])
    assert cmd[:3] == ["prefect", "worker", "start"]
    pool = cmd[cmd.index("--pool") + 1]
    assert pool == POOLS[kind]
    assert pool in {d["work_pool"]["name"] for d in deployments.values()}
    entrypoints = [rest for i, rest in ins if i == "ENTRYPOINT"]
    assert not entrypoints or _exec_form(entrypoints[-1]) == [], "an ENTRYPOINT would prefix the k8s job command"


@pytest.mark.parametrize("kind", sorted(DOCKERFILES))
def test_dockerignore_next_to_dockerfile(kind):
    ignore = DOCKERFILES[kind].with_name(DOCKERFILES[kind].name + ".dockerignore")
    patterns = ignore.read_text().split()
    assert ".venv" in patterns and ".git" in patterns


# --------------------------------------------------------------------------------------------------
# compose.yaml
# --------------------------------------------------------------------------------------------------
def _env(service: dict) -> dict:
    env = service.get("environment", {})
    if isinstance(env, list):
        env = dict(e.split("=", 1) for e in env)
    return env


def _workers(compose) -> dict[str, dict]:
    return {n: s for n, s in compose["services"].items()
            if "worker" in " ".join(map(str, s.get("command", [])))}


def test_compose_images_pinned(compose):
    services = compose["services"]
    assert {"postgres", "prefect-server", "minio", "minio-init"} <= set(services)
    for name, s in services.items():
        image = s.get("image")
        assert image or s.get("build"), f"{name}: no image"
        if image and not s.get("build"):
            tag = image.rpartition(":")[2] if ":" in image.split("/")[-1] else ""
            assert tag and tag != "latest", f"{name}: {image} is not pinned"
    assert services["prefect-server"]["image"].split(":")[1].startswith(prefect.__version__ + "-")


def test_compose_builds_the_worker_images(compose):
    workers = _workers(compose)
    by_pool = {}
    for name, s in workers.items():
        cmd = s["command"]
        by_pool[cmd[cmd.index("--pool") + 1]] = (name, s)
        build = s["build"]
        dockerfile = (COMPOSE.parent / build["context"] / build["dockerfile"]).resolve()
        assert (COMPOSE.parent / build["context"]).resolve() == ROOT
        assert dockerfile in {p.resolve() for p in DOCKERFILES.values()}
    assert set(by_pool) == set(POOLS.values())
    for kind, pool in POOLS.items():
        build = by_pool[pool][1]["build"]
        assert (ROOT / build["dockerfile"]).resolve() == DOCKERFILES[kind].resolve()


def test_compose_env_and_dependencies(compose, deployments):
    services = compose["services"]
    server = _env(services["prefect-server"])
    db = urlparse(server["PREFECT_API_DATABASE_CONNECTION_URL"])
    assert db.scheme == "postgresql+asyncpg" and db.hostname in services
    assert services[db.hostname]["image"].startswith("postgres:")
    assert "server" in services["prefect-server"]["command"]
    pools_used = {d["work_pool"]["name"] for d in deployments.values()}
    for name, s in _workers(compose).items():
        env = _env(s)
        api = urlparse(env["PREFECT_API_URL"])
        assert api.hostname == "prefect-server" and api.path == "/api", f"{name}: {api.geturl()}"
        assert str(api.port) in " ".join(services["prefect-server"]["command"])
        assert env["PREFECT_SERVER_ANALYTICS_ENABLED"] == "false"
        endpoint = urlparse(env["AWS_ENDPOINT_URL"])
        assert endpoint.hostname in services and services[endpoint.hostname]["image"].startswith("minio/minio:")
        assert env["FSSPEC_S3_ENDPOINT_URL"] == env["AWS_ENDPOINT_URL"]
        assert {"AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"} <= set(env)
        assert s["depends_on"]["prefect-server"]["condition"] == "service_healthy"
        assert s["depends_on"]["minio-init"]["condition"] == "service_completed_successfully"
        cmd = s["command"]
        assert cmd[cmd.index("--pool") + 1] in pools_used
    for name, s in services.items():
        for dep, cond in (s.get("depends_on") or {}).items():
            assert dep in services, f"{name} depends on unknown {dep}"
            assert cond["condition"] in {"service_healthy", "service_completed_successfully", "service_started"}
            if cond["condition"] == "service_healthy":
                assert "healthcheck" in services[dep], f"{dep} has no healthcheck"


def test_compose_gpu_reservation(compose):
    workers = {s["command"][s["command"].index("--pool") + 1]: s for s in _workers(compose).values()}
    devices = workers[POOLS["gpu"]]["deploy"]["resources"]["reservations"]["devices"]
    assert any(d.get("driver") == "nvidia" and "gpu" in d.get("capabilities", []) for d in devices)
    assert "deploy" not in workers[POOLS["cpu"]]


# --------------------------------------------------------------------------------------------------
# Kubernetes base job templates
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", sorted(K8S_TEMPLATES))
def test_k8s_base_job_template(kind):
    template = json.loads(K8S_TEMPLATES[kind].read_text())
    assert set(template) == {"job_configuration", "variables"}
    config, variables = template["job_configuration"], template["variables"]
    assert variables["type"] == "object"
    props = variables["properties"]
    used = {p.name for p in find_placeholders(config)}
    assert used <= set(props), f"placeholders without a variable: {used - set(props)}"
    assert {"command", "env", "labels", "name", "namespace", "job_manifest"} <= set(config)
    defaults = {k: v["default"] for k, v in props.items() if "default" in v}
    rendered = apply_values(config, defaults)
    manifest = rendered["job_manifest"]
    # what prefect-kubernetes requires of a job manifest
    assert manifest["apiVersion"] == "batch/v1" and manifest["kind"] == "Job"
    pod = manifest["spec"]["template"]["spec"]
    assert pod["restartPolicy"] == "Never" and pod["parallelism"] == 1 and pod["completions"] == 1
    container = pod["containers"][0]
    assert container["name"] == "prefect-job"
    assert config["job_manifest"]["spec"]["template"]["spec"]["containers"][0]["args"] == "{{ command }}"
    assert container["image"].endswith("-cuda" if kind == "gpu" else "-cpu")
    limits = container["resources"]["limits"]
    if kind == "gpu":
        assert int(limits["nvidia.com/gpu"]) >= 1
        assert any(t.get("key") == "nvidia.com/gpu" for t in pod.get("tolerations", []))
    else:
        assert "nvidia.com/gpu" not in limits and "nvidia.com/gpu" not in container["resources"]["requests"]
    # pods run as the images' non-root user
    uid = re.search(r"--uid (\d+)", DOCKERFILES[kind].read_text()).group(1)
    assert pod["securityContext"]["runAsUser"] == int(uid)

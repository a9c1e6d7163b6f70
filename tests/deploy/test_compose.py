"""deploy/docker-compose.yml and the Dockerfile name only real commands, options, settings and ports.

No Docker needed: the files are parsed and checked against the typer app of quicknav_cli.main,
quicknav_service.settings.Settings, the FastAPI app and pyproject.toml, so a renamed CLI option, setting,
port or route fails here rather than in a container.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import tomllib
import urllib.request
from pathlib import Path
from urllib.parse import urlparse

import pytest
import typer
import yaml
from fastapi.testclient import TestClient

from quicknav_cli.main import app as cli_app
from quicknav_service.api.main import create_app
from quicknav_service.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
COMPOSE_FILE = ROOT / "deploy" / "docker-compose.yml"
DOCKERFILE = ROOT / "Dockerfile"
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
DEFAULT_PORT = Settings.model_fields["port"].default
DEFAULT_GRPC_PORT = Settings.model_fields["grpc_port"].default


# ---------------------------------------------------------------- helpers: compose


def interpolate(value: str, host_env: dict[str, str]) -> str:
    """Compose's ${VAR}, ${VAR:-default}, ${VAR-default}, ${VAR:?err}, $VAR and $$ against host_env."""

    def one(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        name = m.group("braced") or m.group("bare")
        op, arg = m.group("op"), m.group("arg") or ""
        value = host_env.get(name)
        if op in (":-", "-"):
            return arg if value is None or (op == ":-" and value == "") else value
        if op in (":?", "?"):
            if value is None or (op == ":?" and value == ""):
                raise AssertionError(f"compose needs ${name} from the host: {arg}")
            return value
        return value or ""

    pattern = r"\$\$|\$\{(?P<braced>\w+)(?:(?P<op>:?[-?])(?P<arg>[^}]*))?\}|\$(?P<bare>\w+)"
    return re.sub(pattern, one, value)


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE_FILE.read_text())


def quicknav_services(compose: dict) -> dict[str, dict]:
    """Services built from this repository's Dockerfile."""
    out = {}
    for name, svc in compose["services"].items():
        build = svc.get("build")
        if build is None:
            continue
        context = build if isinstance(build, str) else build.get("context", ".")
        dockerfile = (
            "Dockerfile" if isinstance(build, str) else build.get("dockerfile", "Dockerfile")
        )
        assert (COMPOSE_FILE.parent / context / dockerfile).resolve() == DOCKERFILE, name
        out[name] = svc
    return out


def compose_environment(svc: dict, host_env: dict[str, str]) -> dict[str, str]:
    """The variables compose sets in the container; a key without a value is passed from the host
    environment and left unset when the host has none."""
    env = svc.get("environment") or {}
    if isinstance(env, list):
        env = dict(item.split("=", 1) if "=" in item else (item, None) for item in env)
    out = {}
    for key, value in env.items():
        if value is None:
            if key in host_env:
                out[key] = host_env[key]
            continue
        out[key] = interpolate(str(value), host_env)
    return out


def build_args(svc: dict) -> dict[str, str]:
    args = svc["build"].get("args") or {}
    if isinstance(args, list):
        args = dict(item.split("=", 1) for item in args)
    return {k: "" if v is None else str(v) for k, v in args.items()}


def mounts(svc: dict) -> list[tuple[str, str]]:
    """(source, target) of each volume, short or long syntax."""
    out = []
    for v in svc.get("volumes") or []:
        if isinstance(v, str):
            source, target = v.split(":")[:2]
        else:
            source, target = v.get("source", ""), v["target"]
        out.append((source, target))
    return out


def published_ports(svc: dict) -> list[tuple[int, int]]:
    """(host port, container port) of each published port, short or long syntax."""
    out = []
    for p in svc.get("ports") or []:
        if isinstance(p, dict):
            out.append((int(p["published"]), int(p["target"])))
            continue
        spec = interpolate(str(p), {}).split("/")[0]
        *_, host, container = spec.split(":")
        out.append((int(host.split("-")[0]), int(container)))  # a range: its first port
    return out


def published_range(svc: dict) -> range:
    """The host ports of a service's one published port range ("50051-50058:50051")."""
    (p,) = svc.get("ports") or [None]
    host = interpolate(str(p), {}).split("/")[0].split(":")[-2]
    first, _, last = host.partition("-")
    return range(int(first), int(last or first) + 1)


# ---------------------------------------------------------------- helpers: Dockerfile


def dockerfile_stages() -> tuple[list[tuple[str, str]], list[list[tuple[str, str]]]]:
    """(global instructions, [instructions of each stage]); an instruction is (KEYWORD, rest)."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    instructions = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        keyword, _, rest = line.partition(" ")
        instructions.append((keyword.upper(), rest.strip()))
    head, stages = [], []
    for ins in instructions:
        if ins[0] == "FROM":
            stages.append([])
        (stages[-1] if stages else head).append(ins)
    return head, stages


def instruction(stage: list[tuple[str, str]], keyword: str) -> list[str]:
    return [rest for kw, rest in stage if kw == keyword]


def dockerfile_env(stage: list[tuple[str, str]]) -> dict[str, str]:
    env = {}
    for rest in instruction(stage, "ENV"):
        for item in shlex.split(rest):
            key, _, value = item.partition("=")
            env[key] = value
    return env


def final_stage() -> list[tuple[str, str]]:
    return dockerfile_stages()[1][-1]


# ---------------------------------------------------------------- helpers: CLI, settings, health


def parse_cli(argv: list[str]) -> tuple[str, dict]:
    """Parse argv as the `quicknav` command would (unknown command/option or bad value raises);
    returns the subcommand path and its parsed parameters. Nothing runs."""
    assert argv[0] == "quicknav", argv
    command = typer.main.get_command(cli_app)
    ctx, path, args = None, [], list(argv[1:])
    while hasattr(command, "list_commands"):  # a group (typer vendors its own click)
        ctx = command.context_class(command, info_name=" ".join(["quicknav", *path]), parent=ctx)
        assert args and not args[0].startswith("-"), f"{argv}: a subcommand comes first"
        sub = command.get_command(ctx, args[0])
        assert sub is not None, f"{argv}: `quicknav` has no command {args[0]!r}"
        path.append(args.pop(0))
        command = sub
    sub_ctx = command.make_context(path[-1], args, parent=ctx)
    return " ".join(path), sub_ctx.params


def settings_from(env: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> Settings:
    """Settings as a container with exactly these variables builds them; unknown names fail."""
    fields = set(Settings.model_fields)
    unknown = [k for k in env if k.startswith("QUICKNAV_") and k[9:].lower() not in fields]
    assert not unknown, f"not fields of quicknav_service.settings.Settings: {unknown}"
    for key in list(os.environ):
        if key.startswith("QUICKNAV_"):
            monkeypatch.delenv(key)
    for key, value in env.items():
        if key.startswith("QUICKNAV_"):
            monkeypatch.setenv(key, value)
    return Settings(_env_file=None)


def health_url(exec_form: list[str], env: dict[str, str], monkeypatch) -> str:
    """Run a `python -c CODE` health check with urlopen stubbed; returns the URL it opens."""
    assert exec_form[:2] == ["python", "-c"], exec_form
    opened = []
    monkeypatch.setattr(urllib.request, "urlopen", lambda url, *a, **kw: opened.append(url))
    for key in list(os.environ):
        if key.startswith("QUICKNAV_"):
            monkeypatch.delenv(key)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    exec(compile(exec_form[2], "<healthcheck>", "exec"), {})
    assert len(opened) == 1, opened
    return opened[0]


@pytest.fixture(scope="module")
def api_client(tmp_path_factory) -> TestClient:
    settings = Settings(_env_file=None, data_dir=tmp_path_factory.mktemp("data"))
    return TestClient(create_app(settings, start_workers=False))


def service_env(svc: dict) -> dict[str, str]:
    """Image ENV overlaid with the service's environment, host environment empty."""
    return {**dockerfile_env(final_stage()), **compose_environment(svc, host_env={})}


# ---------------------------------------------------------------- compose


def test_compose__every_command_is_a_real_quicknav_command(compose):
    services = quicknav_services(compose)
    assert {"api", "worker"} <= set(services)
    parsed = {name: parse_cli(svc["command"]) for name, svc in services.items()}
    assert parsed["api"] == ("serve", parsed["api"][1])
    assert parsed["api"][1]["no_worker"] is True, "the API leaves jobs to the worker services"
    assert parsed["api"][1]["no_grpc"] is True, "rollouts are served where the GPU is, not by the API"
    for name, (path, params) in parsed.items():
        if name != "api":
            assert path == "worker", name
            assert params["burst"] is False, f"{name} must keep running, not exit when idle"
            assert params["grpc_port"] == DEFAULT_GRPC_PORT, f"{name} serves gRPC Rollout"


def test_compose__quicknav_variables_are_settings_that_validate(compose, monkeypatch):
    for name, svc in quicknav_services(compose).items():
        env = service_env(svc)
        assert any(k.startswith("QUICKNAV_") for k in compose_environment(svc, {})), name
        settings_from(env, monkeypatch)  # raises on an unknown name or a bad value
        # names passed from the host (no value) too
        declared = [k for k in svc.get("environment") or {} if k.startswith("QUICKNAV_")]
        assert {k[9:].lower() for k in declared} <= set(Settings.model_fields), name


def test_compose__api_token_passes_from_the_host_only_when_set(compose, monkeypatch):
    api = compose["services"]["api"]
    assert "QUICKNAV_API_TOKEN" in api["environment"]
    unset = compose_environment(api, host_env={})
    assert "QUICKNAV_API_TOKEN" not in unset or len(unset["QUICKNAV_API_TOKEN"]) >= 8
    token = "t" * 12
    env = {
        **dockerfile_env(final_stage()),
        **compose_environment(api, {"QUICKNAV_API_TOKEN": token}),
    }
    assert settings_from(env, monkeypatch).api_token == token


def test_compose__redis_url_points_at_the_compose_redis_service(compose, monkeypatch):
    for name, svc in quicknav_services(compose).items():
        url = urlparse(settings_from(service_env(svc), monkeypatch).redis_url or "")
        assert url.scheme == "redis", f"{name}: QUICKNAV_REDIS_URL must be set"
        redis = compose["services"].get(url.hostname)
        assert redis is not None, f"{name}: no compose service {url.hostname!r}"
        assert redis["image"].split(":")[0] == "redis"
        assert (url.port or 6379) == 6379
        assert url.hostname in (svc.get("depends_on") or {}), name
        assert svc["depends_on"][url.hostname]["condition"] == "service_healthy", name
    redis = compose["services"]["redis"]
    assert redis["healthcheck"]["test"][-2:] == ["redis-cli", "ping"]
    assert "--appendonly" in redis["command"] and "yes" in redis["command"]
    ((source, target),) = mounts(redis)
    assert source in compose["volumes"] and target == "/data"


def test_compose__published_ports_are_the_settings_ports(compose, monkeypatch):
    api = compose["services"]["api"]
    settings = settings_from(service_env(api), monkeypatch)
    assert settings.port == DEFAULT_PORT
    assert published_ports(api) == [(settings.port, settings.port)], "the API serves HTTP only"
    ranges = []
    for name, svc in quicknav_services(compose).items():
        if name == "api":
            continue
        _, params = parse_cli(svc["command"])
        ((_, container),) = published_ports(svc)
        assert container == params["grpc_port"], f"{name} publishes the port it serves gRPC on"
        # replicas bind 0.0.0.0 (the image's QUICKNAV_HOST), so the port is reachable from outside
        assert settings_from(service_env(svc), monkeypatch).host == "0.0.0.0", name
        ranges.append(published_range(svc))
        assert len(ranges[-1]) >= 4, f"{name}: room for scaled replicas"
    # the workers' host port ranges never collide (any of them may run together)
    for i, a in enumerate(ranges):
        for b in ranges[i + 1 :]:
            assert not set(a) & set(b)
    assert DEFAULT_GRPC_PORT in ranges[0], "the first GPU worker answers on the usual gRPC port"


def test_compose__api_healthcheck_hits_the_health_route(compose, monkeypatch, api_client):
    api = compose["services"]["api"]
    test = api["healthcheck"]["test"]
    assert test[0] == "CMD"
    env = service_env(api)
    settings = settings_from(env, monkeypatch)
    url = urlparse(health_url(test[1:], env, monkeypatch))
    assert (url.hostname, url.port, url.path) == ("127.0.0.1", settings.port, "/healthz")
    assert api_client.get(url.path).status_code == 200


def test_compose__artifacts_volume_is_shared_at_the_data_dir(compose, monkeypatch):
    sources = set()
    for name, svc in quicknav_services(compose).items():
        data_dir = str(settings_from(service_env(svc), monkeypatch).data_dir)
        at_data = [source for source, target in mounts(svc) if target == data_dir]
        assert len(at_data) == 1, f"{name}: nothing mounted at QUICKNAV_DATA_DIR={data_dir}"
        sources.add(at_data[0])
    assert len(sources) == 1, f"API and workers must share one data volume, got {sources}"
    assert sources <= set(compose["volumes"]), "a named volume declared at the top level"


def test_compose__cuda_workers_reserve_a_gpu_and_cpu_services_do_not(compose):
    extras = PYPROJECT["project"]["optional-dependencies"]
    for name, svc in quicknav_services(compose).items():
        jax_extra = build_args(svc).get("JAX_EXTRA", "")
        assert jax_extra in ("", *extras), f"{name}: JAX_EXTRA={jax_extra!r} is no pyproject extra"
        devices = svc.get("deploy", {}).get("resources", {}).get("reservations", {})
        gpus = [
            d
            for d in devices.get("devices", [])
            if d.get("driver") == "nvidia" and "gpu" in d.get("capabilities", [])
        ]
        if jax_extra == "cuda":
            assert len(gpus) == 1, f"{name}: CUDA JAX without a GPU reservation"
            assert gpus[0].get("count") in (1, "all") or gpus[0].get("device_ids"), name
        else:
            assert not gpus, f"{name}: GPU reserved for CPU JAX"
    worker = compose["services"]["worker"]
    assert build_args(worker)["JAX_EXTRA"] == "cuda"
    assert not build_args(compose["services"]["api"]).get("JAX_EXTRA")


# ---------------------------------------------------------------- Dockerfile


def test_dockerfile__cmd_is_quicknav_serve():
    (cmd,) = instruction(final_stage(), "CMD")
    path, params = parse_cli(json.loads(cmd))
    assert path == "serve" and params["no_worker"] is False


def test_dockerfile__exposes_the_settings_ports_and_serves_on_all_interfaces(monkeypatch):
    exposed = {int(p.split("/")[0]) for rest in instruction(final_stage(), "EXPOSE")
               for p in rest.split()}  # fmt: skip
    assert exposed == {DEFAULT_PORT, DEFAULT_GRPC_PORT}
    settings = settings_from(dockerfile_env(final_stage()), monkeypatch)
    assert settings.host == "0.0.0.0"
    assert str(settings.data_dir) == "/data"


def test_dockerfile__healthcheck_follows_quicknav_port(monkeypatch, api_client):
    (rest,) = instruction(final_stage(), "HEALTHCHECK")
    exec_form = json.loads(rest[rest.index("CMD ") + 4 :])
    url = urlparse(health_url(exec_form, {}, monkeypatch))
    assert (url.port, url.path) == (DEFAULT_PORT, "/healthz")
    assert api_client.get(url.path).status_code == 200
    moved = urlparse(health_url(exec_form, {"QUICKNAV_PORT": "9123"}, monkeypatch))
    assert moved.port == 9123


def test_dockerfile__runs_as_a_non_root_user_it_creates():
    stage = final_stage()
    (user,) = instruction(stage, "USER")
    uid = user.split(":")[0]
    assert uid not in ("root", "0")
    created = " ".join(instruction(stage, "RUN"))
    assert re.search(rf"useradd\b.*(--uid {uid}\b|\b{uid}$)", created), f"USER {user} not created"


def test_dockerfile__jax_extra_selects_the_uv_extra():
    head, stages = dockerfile_stages()
    args = [rest for stage in (head, *stages) for rest in instruction(stage, "ARG")]
    assert {'JAX_EXTRA=""', "JAX_EXTRA="} & set(args), "ARG JAX_EXTRA with an empty default (CPU)"
    syncs = [run for stage in stages for run in instruction(stage, "RUN") if "uv sync" in run]
    assert len(syncs) == 2, "dependencies first (a cached layer), then the project"
    for run in syncs:
        assert "--locked" in run and "--no-dev" in run
        assert "--extra service" in run, "the image runs the service: it needs its extra"
        assert '${JAX_EXTRA:+--extra "$JAX_EXTRA"}' in run
    assert "--no-install-workspace" in syncs[0]


def test_dockerfile__copies_what_the_project_build_needs():
    head, stages = dockerfile_stages()
    builder = next(s for s in stages if "uv sync" in " ".join(instruction(s, "RUN")))
    copied = " ".join(instruction(builder, "COPY"))
    needed = [
        "pyproject.toml",
        "uv.lock",
        PYPROJECT["project"]["readme"],
        *PYPROJECT["tool"]["hatch"]["build"]["targets"]["wheel"]["packages"],
        *PYPROJECT["tool"]["uv"]["workspace"]["members"],
        "proto",  # the one home of the .proto the client package builds its stubs from
    ]
    for path in needed:
        assert re.search(rf"(^|\s){re.escape(path)}(\s|$)", copied), f"{path} is not copied"
    mounted = " ".join(instruction(builder, "RUN"))
    for member in PYPROJECT["tool"]["uv"]["workspace"]["members"]:
        assert f"source={member}/pyproject.toml" in mounted, "the dependency layer needs it"


def test_dockerfile__runtime_runs_the_builders_venv_on_the_same_python():
    uv_images = re.findall(r"ghcr\.io/astral-sh/uv(\S*)", DOCKERFILE.read_text())
    assert uv_images and all(re.fullmatch(r":\d+\.\d+\.\d+", tag) for tag in uv_images), uv_images
    _, stages = dockerfile_stages()
    builder = next(s for s in stages if "uv sync" in " ".join(instruction(s, "RUN")))
    base, _, builder_name = instruction(builder, "FROM")[0].partition(" AS ")
    # the venv's interpreter is a symlink into the base image: both stages need the same base
    assert instruction(final_stage(), "FROM")[0].split()[0] == base.strip()
    env = dockerfile_env(builder)
    venv = env["UV_PROJECT_ENVIRONMENT"]
    assert env["UV_COMPILE_BYTECODE"] == "1"
    assert f"--from={builder_name.strip()} {venv} {venv}" in instruction(final_stage(), "COPY")
    assert dockerfile_env(final_stage())["PATH"].startswith(f"{venv}/bin:")


def test_deploy_readme__names_only_real_variables():
    text = (ROOT / "deploy" / "README.md").read_text()
    names = set(re.findall(r"QUICKNAV_[A-Z_]+", text))
    # read outside Settings: by the CLI, or by compose itself when it interpolates the file
    elsewhere = {
        "QUICKNAV_JAX_CACHE": (ROOT / "quicknav_cli" / "common.py").read_text(),
        "QUICKNAV_PUBLISH_ADDR": COMPOSE_FILE.read_text(),
    }
    for name in names:
        if name in elsewhere:
            assert name in elsewhere[name], f"{name} is no longer read"
        else:
            assert name[9:].lower() in Settings.model_fields, f"deploy/README.md: {name}"


def test_lock__the_cuda_extra_resolves_to_cuda_13_plugins_matching_jaxlib():
    """`uv sync --extra cuda` installs from uv.lock (CI runs `uv sync --locked`, which fails on a
    stale lock): the extra must be locked, for CUDA 13 (the GPUs' driver), at jaxlib's version."""
    import tomllib

    root = Path(__file__).resolve().parents[2]
    lock = tomllib.loads((root / "uv.lock").read_text())
    packages = lock["package"]

    def versions(name: str) -> set[str]:
        return {p["version"] for p in packages if p["name"] == name}

    (ours,) = [p for p in packages if p["name"] == "quicknav"]
    cuda = ours["optional-dependencies"]["cuda"]
    # one jax per Python fork of the lock, each with the cuda13 extra
    assert {d["name"] for d in cuda} == {"jax"} and all("cuda13" in d["extra"] for d in cuda)
    assert {d["version"] for d in cuda} <= versions("jax-cuda13-plugin")
    assert versions("jax-cuda13-plugin") and versions("jax-cuda13-pjrt")
    assert versions("jax-cuda13-plugin") <= versions("jaxlib")
    assert versions("jax-cuda13-pjrt") == versions("jax-cuda13-plugin")

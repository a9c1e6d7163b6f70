"""deploy/kubernetes validates against the Kubernetes schemas and names only real commands,
settings, ports, routes and Redis keys.

No cluster needed: kubernetes-validate checks every core object against the schemas it bundles
(strict: an unknown field fails); the rest is checked against the typer app, Settings, the FastAPI
app and the Redis store's key names, as tests/deploy/test_compose.py does for compose.
"""

from __future__ import annotations

import inspect
from pathlib import Path

import kubernetes_validate
import pytest
import yaml

from quicknav_service.jobs.redis_store import GROUP, RedisJobStore
from quicknav_service.settings import Settings
from tests.deploy.test_compose import api_client, parse_cli, settings_from  # noqa: F401

ROOT = Path(__file__).resolve().parents[2]
BASE = ROOT / "deploy" / "kubernetes"
K8S_VERSION = "1.33"  # the oldest release still supported upstream when these were written
DEFAULT_PORT = Settings.model_fields["port"].default
DEFAULT_GRPC_PORT = Settings.model_fields["grpc_port"].default


def load(folder: Path) -> list[dict]:
    """Every object a kustomization lists, following other kustomizations it names."""
    kustomization = yaml.safe_load((folder / "kustomization.yaml").read_text())
    objects = []
    for resource in kustomization["resources"]:
        path = (folder / resource).resolve()
        if path.is_dir():
            objects += load(path)
        else:
            objects += [doc for doc in yaml.safe_load_all(path.read_text()) if doc]
    return objects


@pytest.fixture(scope="module")
def base() -> dict[tuple[str, str], dict]:
    return {(o["kind"], o["metadata"]["name"]): o for o in load(BASE)}


def deployments(base) -> dict[str, dict]:
    return {name: o for (kind, name), o in base.items() if kind == "Deployment"}


def quicknav_containers(base) -> dict[str, dict]:
    out = {}
    for name, d in deployments(base).items():
        for c in d["spec"]["template"]["spec"]["containers"]:
            if c["image"].startswith("quicknav:"):
                out[name] = c
    return out


def container_env(base, container: dict) -> dict[str, str]:
    """What a container's environment holds: its ConfigMaps, then its own entries (values only)."""
    env = {}
    for source in container.get("envFrom", []):
        if "configMapRef" in source:
            env.update(base[("ConfigMap", source["configMapRef"]["name"])]["data"])
    for item in container.get("env", []):
        env[item["name"]] = item.get("value", "10.0.0.7")  # a fieldRef: a pod IP
    return env


def test_kubernetes__every_core_object_validates_against_the_schemas(base):
    kinds = {kind for kind, _ in base}
    assert {"Deployment", "Service", "ConfigMap", "PersistentVolumeClaim"} <= kinds
    for obj in base.values():
        kubernetes_validate.validate(obj, K8S_VERSION, strict=True)  # raises on any error


def test_kubernetes__a_broken_object_is_caught_by_the_validation(base):
    broken = yaml.safe_load(yaml.safe_dump(base[("Deployment", "api")]))
    broken["spec"]["template"]["spec"]["containers"][0]["livenessProbe"]["httpGet"]["paht"] = "/x"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(broken, K8S_VERSION, strict=True)


def test_kubernetes__every_command_is_a_real_quicknav_command(base):
    parsed = {name: parse_cli(c["command"]) for name, c in quicknav_containers(base).items()}
    assert set(parsed) == {"api", "worker-gpu", "worker-cpu"}
    path, params = parsed["api"]
    assert path == "serve" and params["no_worker"] and params["no_grpc"]
    for name in ("worker-gpu", "worker-cpu"):
        path, params = parsed[name]
        assert path == "worker" and params["burst"] is False
        assert params["grpc_port"] == DEFAULT_GRPC_PORT


def test_kubernetes__settings_are_real_and_validate(base, monkeypatch):
    for name, c in quicknav_containers(base).items():
        settings = settings_from(container_env(base, c), monkeypatch)
        assert settings.redis_url == "redis://redis:6379/0", name
        assert str(settings.data_dir) == "/data"
        assert any(s.get("secretRef", {}).get("optional") for s in c["envFrom"]), name
        # the artifacts on the object store, its credentials from a Secret every container needs
        assert settings.artifacts_url == "s3://quicknav/artifacts", name
        assert {"name": "quicknav-artifacts"} in [s.get("secretRef") for s in c["envFrom"]], name


def test_kubernetes__ports_services_and_the_redis_url_agree(base):
    containers = quicknav_containers(base)
    assert [p["containerPort"] for p in containers["api"]["ports"]] == [DEFAULT_PORT]
    for name in ("worker-gpu", "worker-cpu"):
        assert [p["containerPort"] for p in containers[name]["ports"]] == [DEFAULT_GRPC_PORT]
    for (kind, name), svc in base.items():
        if kind != "Service":
            continue
        target = deployments(base)[{"api": "api", "redis": "redis"}[name]]
        labels = target["spec"]["template"]["metadata"]["labels"]
        assert svc["spec"]["selector"].items() <= labels.items(), name
        ports = {p["name"]: p["containerPort"] for c in target["spec"]["template"]["spec"]["containers"]
                 for p in c["ports"]}  # fmt: skip
        for p in svc["spec"]["ports"]:
            assert p["targetPort"] in ports, (name, p)
    redis_port = base[("Service", "redis")]["spec"]["ports"][0]["port"]
    assert base[("ConfigMap", "quicknav")]["data"]["QUICKNAV_REDIS_URL"] == f"redis://redis:{redis_port}/0"


def test_kubernetes__probes_hit_real_routes_and_the_workers_grpc_health(base, api_client):  # noqa: F811
    api = quicknav_containers(base)["api"]
    paths = {name: api[name]["httpGet"]["path"] for name in ("livenessProbe", "readinessProbe", "startupProbe")}
    assert paths["readinessProbe"] == "/readyz" and paths["livenessProbe"] == "/healthz"
    for path in paths.values():
        assert api_client.get(path).status_code == 200, path
    for name in ("worker-gpu", "worker-cpu"):
        c = quicknav_containers(base)[name]
        for probe in ("livenessProbe", "readinessProbe", "startupProbe"):
            assert c[probe]["grpc"]["port"] == DEFAULT_GRPC_PORT, (name, probe)


def test_kubernetes__gpu_workers_take_a_gpu_and_drain_on_sigterm(base):
    d = deployments(base)
    gpu = quicknav_containers(base)["worker-gpu"]["resources"]
    assert gpu["limits"]["nvidia.com/gpu"] == 1
    for name in ("api", "worker-cpu"):
        resources = quicknav_containers(base)[name]["resources"]
        assert "nvidia.com/gpu" not in {**resources.get("limits", {}), **resources.get("requests", {})}
    for name in ("worker-gpu", "worker-cpu"):
        # a worker stops at its next chunk boundary: a chunk of the presets takes well under this
        assert d[name]["spec"]["template"]["spec"]["terminationGracePeriodSeconds"] >= 120
    for name in ("api", "worker-gpu", "worker-cpu"):
        # no shared filesystem: /data is each pod's own scratch, the artifacts are in the bucket
        mounts = {m["mountPath"] for m in quicknav_containers(base)[name]["volumeMounts"]}
        volumes = d[name]["spec"]["template"]["spec"]["volumes"]
        assert mounts == {"/data"} and [set(v) for v in volumes] == [{"name", "emptyDir"}], name
    assert not any(o["spec"].get("accessModes") == ["ReadWriteMany"]
                   for (kind, _), o in base.items() if kind == "PersistentVolumeClaim")  # fmt: skip


def test_kubernetes__keda_scales_the_workers_on_the_stores_real_queue(base):
    scaled = [o for o in load(BASE / "keda") if o["kind"] == "ScaledObject"]
    assert {o["spec"]["scaleTargetRef"]["name"] for o in scaled} == {"worker-gpu", "worker-cpu"}
    redis_svc = base[("Service", "redis")]
    redis_port = redis_svc["spec"]["ports"][0]["port"]
    for o in scaled:
        assert o["spec"]["scaleTargetRef"]["name"] in deployments(base)
        for trigger in o["spec"]["triggers"]:
            meta = trigger["metadata"]
            assert trigger["type"] == "redis-streams"
            # the Redis store's queue: prefix "quicknav", the stream "queue", its consumer group
            prefix = inspect.signature(RedisJobStore).parameters["prefix"].default
            assert meta["stream"] == f"{prefix}:queue" and meta["consumerGroup"] == GROUP
            assert meta["address"] == f"redis.quicknav.svc:{redis_port}"
            assert {"lagCount", "pendingEntriesCount"} & set(meta)
    # and the base alone (no KEDA installed) has no object of KEDA's
    assert not [k for k, _ in base if k == "ScaledObject"]

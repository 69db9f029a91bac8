"""The image's build files, read without building it: `deploy/Dockerfile` and its build arguments,
the packages it installs (`deploy/requirements.txt`, pinned by `deploy/constraints.txt`), what
`.dockerignore` lets into the build context, and the Makefile's image targets. `make image-test`
(tests/image/run.py, not part of `make test`) builds the CPU image and runs it."""

from __future__ import annotations

import re
import shlex
import subprocess
from fnmatch import fnmatch
from pathlib import Path

import pytest
import tomllib

from tests.support.paths import REPO

DEPLOY = REPO / "deploy"
DOCKERFILE = DEPLOY / "Dockerfile"

# Published torch builds, from PyTorch's CUDA support matrix and the wheels on PyPI: CUDA
# major.minor and CPython versions per torch minor release. Add the release before pinning it.
TORCH_CUDA_BUILDS = {"2.13": {"12.6", "13.0", "13.2"}}
TORCH_PYTHONS = {"2.13": {"3.10", "3.11", "3.12", "3.13", "3.14"}}
# The python3 of each Ubuntu release the NVIDIA CUDA images are built on.
UBUNTU_PYTHON = {"22.04": "3.10", "24.04": "3.12"}
#: What the image installed before its package list moved to requirements.txt (the GPU image
#: installs exactly these still), after torch.
INSTALLED = [
    "numpy",
    "pyyaml",
    "tqdm",
    "matplotlib",
    "scipy",
    "ray[default,data,serve]",
    "fastapi",
    "starlette",
    "uvicorn[standard]",
    "python-multipart",
    "pydantic",
    "pydantic-settings",
    "httpx",
    "prometheus-client",
    "onnx",
    "onnxscript",
    "onnxruntime",
    "huggingface_hub",
    "pypcd4",
    "laspy[lazrs]",
    "rosbags",
]


def _text() -> str:
    return DOCKERFILE.read_text()


def _build_args() -> dict[str, str]:
    """Every ARG of the Dockerfile with its default ("" for an ARG given `=""` or none)."""
    found = {}
    for name, value in re.findall(r"^ARG (\w+)(?:=(\S*))?$", _text(), flags=re.M):
        found[name] = value.strip('"')
    return found


def _runs() -> list[str]:
    """The shell of every RUN instruction, continuation lines joined, `--mount` options left out."""
    text = _text().replace("\\\n", " ")
    runs = re.findall(r"^RUN (.+)$", text, flags=re.M)
    return [re.sub(r"^(--mount=\S+\s+)+", "", run) for run in runs]


def _names(requirements: list[str]) -> set[str]:
    return {
        re.split(r"[<>=\[ ;]", r, maxsplit=1)[0].lower().replace("_", "-") for r in requirements
    }


def _requirements() -> list[str]:
    lines = (DEPLOY / "requirements.txt").read_text().splitlines()
    return [line.strip() for line in lines if line.strip() and not line.startswith("#")]


def _constraints() -> dict[str, str]:
    lines = (DEPLOY / "constraints.txt").read_text().splitlines()
    pins = dict(line.split("==") for line in lines if line and not line.startswith("#"))
    return {name.lower().replace("_", "-"): version for name, version in pins.items()}


def test_the_build_arguments_have_their_defaults():
    """The GPU image by default: the CUDA runtime base of CUDA_VERSION, its Python, torch's build
    for that CUDA (derived), packages from PyPI (no wheelhouse), no baked weights."""
    assert _build_args() == {
        "CUDA_VERSION": "13.0.2",
        "BASE_IMAGE": "nvidia/cuda:${CUDA_VERSION}-cudnn-runtime-ubuntu24.04",
        "PYTHON": "python3.12",
        "TORCH_BUILD": "",
        "WHEELHOUSE": "",
        "RANGERET_WEIGHTS": "",
    }
    text = _text()
    before_from = text.split("\nFROM ", 1)[0]
    assert "ARG CUDA_VERSION" in before_from and "ARG BASE_IMAGE" in before_from
    assert re.findall(r"^FROM (.+)$", text, flags=re.M) == ["${BASE_IMAGE}"]  # no node stage


def _run_install(tmp_path: Path, env: dict[str, str], wheels: list[str] = ()):
    """The Dockerfile's dependency RUN, executed by sh with `pip` and `python` stubs that record
    their arguments; /wheelhouse is a folder of the test holding `wheels`. Returns the exit code,
    the recorded pip commands and stderr."""
    (run,) = [r for r in _runs() if "-c deploy/constraints.txt torch" in r]
    house = tmp_path / "wheelhouse"
    for wheel in wheels:
        (house / env.get("WHEELHOUSE", "")).mkdir(parents=True, exist_ok=True)
        (house / env.get("WHEELHOUSE", "") / wheel).touch()
    bindir = tmp_path / "bin"
    bindir.mkdir(exist_ok=True)
    record = tmp_path / "pip.log"
    record.write_text("")
    (bindir / "pip").write_text(f'#!/bin/sh\necho "$*" >> {record}\n')
    (bindir / "python").write_text("#!/bin/sh\nexit 0\n")
    for stub in ("pip", "python"):
        (bindir / stub).chmod(0o755)
    script = run.replace("/wheelhouse", str(house))
    done = subprocess.run(
        ["sh", "-c", script],
        env={"PATH": f"{bindir}:/usr/bin:/bin", **env},
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    return done.returncode, record.read_text().splitlines(), done.stderr


def test_the_gpu_path_installs_torch_of_the_base_images_cuda_then_the_pinned_packages(tmp_path):
    """With the default arguments on the CUDA base (which sets CUDA_VERSION), torch comes from
    the wheel index of that CUDA and the rest from PyPI, each pinned by constraints.txt."""
    code, pip, err = _run_install(tmp_path, {"CUDA_VERSION": _build_args()["CUDA_VERSION"]})
    assert code == 0, err
    assert pip == [
        "install --extra-index-url https://download.pytorch.org/whl/cu130 "
        "-c deploy/constraints.txt torch",
        "install -c deploy/constraints.txt -r deploy/requirements.txt",
    ]
    # The build checks the installed wheel's CUDA against the build it asked for.
    (run,) = [r for r in _runs() if "-c deploy/constraints.txt torch" in r]
    assert "torch.version.cuda" in run


def test_the_gpu_path_installs_what_constraints_txt_pins():
    """The GPU image's package list (torch, then requirements.txt) names every package that
    constraints.txt pins and no other, and is the list the image installed before; a package an
    extra brings (laspy[lazrs]) counts as named."""
    requirements = _requirements()
    assert requirements == INSTALLED
    named = {"torch"} | _names(requirements)
    extras = {e for r in requirements for e in re.findall(r"\[([^\]]+)\]", r)[0:1]}
    brought = {e.strip() for group in extras for e in group.split(",")}
    assert named <= set(_constraints())
    assert set(_constraints()) <= named | brought
    assert set(_constraints()) - named == {"lazrs"}  # from laspy[lazrs]


def test_the_image_installs_every_dependency_of_the_project_and_its_extras():
    """The project is installed with --no-deps, so the package list must name every dependency
    of pyproject.toml and of the extras the image serves (all but ros2 and dev)."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    wanted = list(project["dependencies"])
    for extra in ("ray", "gateway", "onnx", "hub", "files", "bags"):
        wanted += project["optional-dependencies"][extra]
    installed = {"torch"} | _names(_requirements())
    assert _names(wanted) <= installed
    pins = _constraints()
    ray = next(r for r in project["optional-dependencies"]["ray"] if r.startswith("ray["))
    assert ray.endswith(f"=={pins['ray']}")
    assert "ray[default,data,serve]" in _requirements()


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        ({"TORCH_BUILD": "cu126", "CUDA_VERSION": "13.0.2"}, "TORCH_BUILD=cu126"),
        ({}, "TORCH_BUILD=cu:"),  # a base without CUDA and no TORCH_BUILD
    ],
)
def test_a_torch_build_that_does_not_fit_the_base_stops_the_build(tmp_path, env, expected):
    code, pip, err = _run_install(tmp_path, env)
    assert code != 0 and pip == [] and expected in err


def test_a_wheelhouse_installs_everything_with_no_index(tmp_path):
    """WHEELHOUSE=NAME: torch and the rest from deploy/wheelhouse/NAME alone (no index, no torch
    index); the project's own install takes its build backend from there too. An empty one stops
    the build with a sentence naming `make wheelhouse`."""
    env = {"TORCH_BUILD": "cpu", "WHEELHOUSE": "cpu-py3.11"}
    code, pip, err = _run_install(tmp_path, env, ["torch-2.13.0+cpu-cp311-cp311-x.whl"])
    assert code == 0, err
    house = f"--no-index --find-links {tmp_path}/wheelhouse/cpu-py3.11"
    assert pip == [
        f"install {house} -c deploy/constraints.txt torch",
        f"install {house} -c deploy/constraints.txt -r deploy/requirements.txt",
    ]
    empty = tmp_path / "empty"
    empty.mkdir()
    code, pip, err = _run_install(empty, env)
    assert code != 0 and "make wheelhouse" in err and pip == []
    (project,) = [r for r in _runs() if "--no-deps ." in r]
    assert "--no-index --find-links /wheelhouse/$WHEELHOUSE" in project
    # The wheelhouse is mounted for those two RUNs only, never copied into a layer.
    mounts = re.findall(r"--mount=type=bind,source=deploy/wheelhouse,target=/wheelhouse", _text())
    assert len(mounts) == 2 and "COPY deploy/wheelhouse" not in _text()


def test_the_system_packages_come_from_apt_only_when_the_base_lacks_them():
    (run,) = [r for r in _runs() if "dpkg -s" in r]
    assert (
        'packages="${PYTHON} ${PYTHON}-venv tini ca-certificates rsync openssh-client gcc libc6-dev"'
        in run
    )
    assert (
        'if [ -n "$missing" ]' in run
        and "apt-get install -y --no-install-recommends $missing" in run
    )
    assert "${PYTHON} -m venv /opt/rangeret" in run


def _pyproject_packages() -> list[str]:
    """The top-level packages pyproject.toml installs (its setuptools `find` includes)."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    includes = config["tool"]["setuptools"]["packages"]["find"]["include"]
    return sorted(pattern.rstrip("*") for pattern in includes)


def test_every_package_pyproject_installs_is_copied():
    """Each top-level package (ros2node too: the `rangeret` command loads its entry point, and
    a missing module would be a warning on every command) and the files pip needs."""
    text = _text()
    for package in _pyproject_packages():
        assert f"COPY {package} /app/{package}\n" in text, package
        assert (REPO / package / "__init__.py").is_file(), package
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    for group in config["project"]["entry-points"].values():
        for target in group.values():
            assert target.split(".")[0] in _pyproject_packages(), target
    assert "COPY pyproject.toml setup.py README.md /app/" in text
    for source in re.findall(r"^COPY (?!--from=)(.+) \S+$", text, flags=re.M):
        for item in source.split():
            assert (REPO / item).exists(), item


def test_the_image_runs_the_entrypoint_as_uid_10001_with_a_health_check():
    text = _text()
    assert "useradd --create-home --uid 10001 rangeret" in text and "USER rangeret" in text
    # KubeRay's `ray start` runs without the entrypoint: the image's environment must carry it.
    assert re.search(r"^ENV .*PATH=/opt/rangeret/bin:\$PATH", text, flags=re.M | re.S)
    assert "RAY_AUTH_MODE=token" in text
    assert 'ENTRYPOINT ["tini", "--", "/app/deploy/entrypoint.sh"]' in text
    assert 'CMD ["gateway"]' in text
    assert 'CMD ["python", "/app/deploy/healthcheck.py"]' in text
    assert re.search(r"^EXPOSE (.+)$", text, flags=re.M).group(1).split() == [
        "8000",
        "6379",
        "8265",
    ]  # no Ray Client (10001)
    subprocess.run(["bash", "-n", str(DEPLOY / "entrypoint.sh")], check=True)


def test_base_cuda_python_and_torch_wheel_match():
    """The default base image's CUDA has a torch build, its Python has torch wheels, the
    Dockerfile's PYTHON is that Python, and torch is pinned in one place (the Makefile's
    TORCH_SPEC is constraints.txt's pin)."""
    args = _build_args()
    base = args["BASE_IMAGE"].replace("${CUDA_VERSION}", args["CUDA_VERSION"])
    match = re.fullmatch(r"nvidia/cuda:((\d+)\.(\d+)\.\d+)-cudnn-runtime-ubuntu(\d+\.\d+)", base)
    assert match, base
    _, major, minor, ubuntu = match.groups()
    makefile = (REPO / "Makefile").read_text()
    torch_spec = re.search(r"^TORCH_SPEC \?= (\S+)$", makefile, flags=re.M).group(1)
    assert f"torch=={_constraints()['torch']}" == torch_spec
    release = ".".join(_constraints()["torch"].split(".")[:2])
    assert f"{major}.{minor}" in TORCH_CUDA_BUILDS[release]
    assert args["PYTHON"] == f"python{UBUNTU_PYTHON[ubuntu]}"
    assert UBUNTU_PYTHON[ubuntu] in TORCH_PYTHONS[release]
    assert "3.11" in TORCH_PYTHONS[release]  # the CPU variant's Python (Debian bookworm)
    assert set(re.findall(r"torch==(\d[\w.]*\d)", _text())) <= {_constraints()["torch"]}
    # The documented build commands name the same CUDA pin.
    for doc in (DEPLOY / "README.md", REPO / "docs" / "deploy.md", DOCKERFILE):
        builds = re.findall(
            r"docker build -f deploy/Dockerfile --build-arg CUDA_VERSION=(\S+) -t \S+ \.",
            doc.read_text(),
        )
        assert builds == [args["CUDA_VERSION"]], doc.name


# --- the build context ------------------------------------------------------------------------


def _ignore_rules() -> list[tuple[bool, re.Pattern]]:
    """.dockerignore as (excludes, regex) rules, in Docker's syntax: `*` and `?` within one path
    element, `**` across any number, a leading `!` lets a path through again, the last rule that
    matches a path or one of its parent folders decides."""
    rules = []
    for line in (REPO / ".dockerignore").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        excludes = not line.startswith("!")
        pattern = line.lstrip("!").strip("/")
        regex = ""
        i = 0
        while i < len(pattern):
            if pattern.startswith("**/", i):
                regex += "(?:.*/)?"
                i += 3
            elif pattern.startswith("**", i):
                regex += ".*"
                i += 2
            elif pattern[i] == "*":
                regex += "[^/]*"
                i += 1
            elif pattern[i] == "?":
                regex += "[^/]"
                i += 1
            else:
                regex += re.escape(pattern[i])
                i += 1
        rules.append((excludes, re.compile(regex + "$")))
    return rules


def _in_context(path: str, rules: list[tuple[bool, re.Pattern]]) -> bool:
    parts = path.split("/")
    prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    excluded = False
    for excludes, regex in rules:
        if any(regex.match(prefix) for prefix in prefixes):
            excluded = excludes
    return not excluded


def _repo_files() -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    web = REPO / "service" / "web" / "node_modules"
    listed += [p.relative_to(REPO).as_posix() for p in web.rglob("*") if p.is_file()]
    return sorted(set(listed))


def test_dockerignore_lets_exactly_what_the_image_takes_into_the_build_context():
    """Of the npm packages `make web` installs, only the files the gateway serves (and three.js's
    licence and package.json); the project's packages, pyproject.toml, setup.py and README.md; of deploy/,
    the files the image copies and the wheelhouse; nothing else (no tests, docs, .venv, runs)."""
    from service.page_assets import VENDOR_FILES

    rules = _ignore_rules()
    files = _repo_files()
    kept = [f for f in files if _in_context(f, rules)]
    npm = {
        f.removeprefix("service/web/node_modules/")
        for f in kept
        if f.startswith("service/web/node_modules/")
    }
    assert npm == {*VENDOR_FILES, "three/LICENSE", "three/package.json", "swagger-ui-dist/LICENSE"}
    copied = re.findall(r"^COPY (?!--from=)(.+) \S+$", _text(), flags=re.M)
    for source in " ".join(copied).split():
        if (REPO / source).is_file():
            assert _in_context(source, rules), source
        else:
            inside = [
                f
                for f in files
                if f.startswith(source + "/")
                and "__pycache__" not in f
                and not f.startswith("service/web/node_modules/")  # its own COPY lines
            ]
            assert inside and all(_in_context(f, rules) for f in inside), source
    packages = tuple(f"{p}/" for p in _pyproject_packages())
    for path in kept:
        assert (
            path.startswith(packages)
            or path in ("pyproject.toml", "setup.py", "README.md")
            or path.startswith("deploy/wheelhouse/")
            or path in {f"deploy/{n}" for n in ("constraints.txt", "requirements.txt",
                                                "entrypoint.sh", "healthcheck.py")}
        ), path  # fmt: skip
        assert "__pycache__" not in path and not path.endswith(".pyc"), path
    assert _in_context("deploy/wheelhouse/cpu-py3.11/torch.whl", rules)
    for outside in ("tests/conftest.py", ".venv/bin/python", "runs/x", "docs/deploy.md",
                    "service/web/node_modules/.installed", "deploy/Dockerfile"):  # fmt: skip
        assert not _in_context(outside, rules), outside
    # The web files are copied from the context (no node stage, no npm ci in the build).
    assert "npm" not in _text().replace("npm packages", "")


# --- the Makefile ---------------------------------------------------------------------------


def _make(*args: str) -> str:
    """`make -n` (print, do not run) of a target with the given variables, continued lines
    joined (a stamp's recipe comes first when the stamp is out of date)."""
    done = subprocess.run(
        ["make", "-n", "--no-print-directory", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    return done.stdout.replace("\\\n", " ")


def test_make_image_builds_with_the_container_tool_and_the_variants_arguments():
    gpu = _make("image", "CONTAINER=docker").splitlines()[-1]
    assert shlex.split(gpu)[:4] == ["docker", "build", "-f", "deploy/Dockerfile"]
    assert "--build-arg TORCH_BUILD=cu130" in gpu and "--build-arg PYTHON=python3.12" in gpu
    assert (
        "BASE_IMAGE" not in gpu
        and "--network none" not in gpu
        and gpu.endswith("-t rangeret:0.1.0 .")
    )
    cpu = _make(
        "image", "VARIANT=cpu", "CONTAINER=podman", "OFFLINE=1", "BASE_IMAGE=localhost/base:x"
    ).splitlines()[-1]
    argv = shlex.split(cpu)
    assert argv[:2] == ["podman", "build"] and "--format" in argv  # HEALTHCHECK kept
    for flag in ("--build-arg TORCH_BUILD=cpu", "--build-arg PYTHON=python3.11",
                 "--build-arg BASE_IMAGE=localhost/base:x",
                 "--build-arg WHEELHOUSE=cpu-py3.11 --network none"):  # fmt: skip
        assert flag in cpu, flag
    assert cpu.endswith("-t rangeret:0.1.0-cpu .")
    cpu_default = _make("image", "VARIANT=cpu", "CONTAINER=docker").splitlines()[-1]
    assert "--build-arg BASE_IMAGE=debian:bookworm-slim" in cpu_default
    # Without CONTAINER: the first of docker and podman whose `info` succeeds.
    makefile = (REPO / "Makefile").read_text()
    assert "for c in docker podman; do $$c info >/dev/null 2>&1" in makefile


def test_make_wheelhouse_downloads_for_the_images_python_and_platform():
    lines = [line for line in _make("wheelhouse", "VARIANT=cpu").splitlines() if "download" in line]
    torch, rest = (shlex.split(line) for line in lines)
    for argv in (torch, rest):
        assert argv[argv.index("--dest") + 1] == "deploy/wheelhouse/cpu-py3.11"
        assert "--only-binary=:all:" in argv and argv[argv.index("--python-version") + 1] == "3.11"
        platforms = [argv[i + 1] for i, a in enumerate(argv) if a == "--platform"]
        assert "manylinux_2_36_x86_64" in platforms and "manylinux_2_28_x86_64" in platforms
        assert "manylinux2014_x86_64" in platforms
        assert argv[argv.index("-c") + 1] == "deploy/constraints.txt"
    assert torch[-1] == "torch"
    assert torch[torch.index("--extra-index-url") + 1] == "https://download.pytorch.org/whl/cpu"
    assert "-r" in rest and rest[rest.index("-r") + 1] == "deploy/requirements.txt"
    assert "--extra-index-url" not in rest  # only torch comes from its index
    gpu = _make("wheelhouse").splitlines()
    assert any("deploy/wheelhouse/cu130-py3.12" in line and "manylinux_2_39_x86_64" in line
               for line in gpu)  # fmt: skip


def test_the_image_test_is_outside_make_test_and_said_so():
    makefile = (REPO / "Makefile").read_text()
    test_rule = re.search(r"^test: (.*)$", makefile, flags=re.M).group(1).split()
    assert "image-test" not in test_rule and "podman" not in test_rule
    assert re.search(r"^image-test: .*podman", makefile, flags=re.M)
    assert "$(BIN)/python -m tests.image.run" in makefile
    readme = (REPO / "README.md").read_text()
    assert "make image-test" in readme
    # pytest does not collect the image test.
    assert not fnmatch("run.py", "test_*.py") and not fnmatch("run.py", "*_test.py")

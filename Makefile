# The two commands of the quick start: `make demo` (the main job) and `make test` (the whole suite);
# `make check` is the fast loop: lint and the tests not marked slow.
# Both build the virtual environment in .venv and the gateway's web page (`make web`) on first use;
# `make test` also installs chromium for the browser tests (as root; otherwise it names the command).
# The environment holds every extra (`.[all,dev]`: Ray, the gateway, ONNX, the hub, the test tools).

PYTHON ?= python3
# The CPU build of torch found on this machine kind; on a GPU machine pass e.g. TORCH_SPEC=torch==2.13.0
# with your CUDA wheel index, or install torch into .venv yourself first.
TORCH_SPEC ?= torch==2.13.0
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= runs/demo
# The web page's npm packages (three.js, pinned by package-lock.json), installed once by npm ci.
WEB := service/web
WEB_STAMP := $(WEB)/node_modules/.installed
CHROMIUM_INSTALL := apt-get update && apt-get install -y --no-install-recommends chromium
IPROUTE_INSTALL := apt-get update && apt-get install -y --no-install-recommends iproute2

# The service image (deploy/Dockerfile), `make image`: VARIANT=gpu (the default: the CUDA runtime
# base, torch's cu130 build, Python 3.12) or VARIANT=cpu (Debian bookworm, torch's CPU build,
# Python 3.11); IMAGE names it. CONTAINER: docker or podman, by default the first of them whose
# `info` succeeds. BASE_IMAGE replaces the variant's base. OFFLINE=1 installs every Python package
# from the variant's wheelhouse, deploy/wheelhouse/$(TORCH_BUILD)-py$(IMAGE_PYTHON), which
# `make wheelhouse` fills (pip download of the pinned requirements for the image's Python and
# platform, torch from TORCH_INDEX: empty takes the torch build pip finds with its own
# configuration), and builds with no network.
VARIANT ?= gpu
ifeq ($(VARIANT),cpu)
IMAGE ?= rangeret:0.1.0-cpu
BASE_IMAGE ?= debian:bookworm-slim
IMAGE_PYTHON ?= 3.11
IMAGE_GLIBC ?= 36
TORCH_BUILD ?= cpu
else
IMAGE ?= rangeret:0.1.0
BASE_IMAGE ?=
IMAGE_PYTHON ?= 3.12
IMAGE_GLIBC ?= 39
TORCH_BUILD ?= cu130
endif
TORCH_INDEX ?= https://download.pytorch.org/whl/$(TORCH_BUILD)
WHEELHOUSE := $(TORCH_BUILD)-py$(IMAGE_PYTHON)
CONTAINER ?= $(shell for c in docker podman; do $$c info >/dev/null 2>&1 && { echo $$c; break; }; done)
# pip download for the image's Python and platform: manylinux wheels up to the base's glibc.
IMAGE_WHEELS := --only-binary=:all: --python-version $(IMAGE_PYTHON) --implementation cp \
	--abi cp$(subst .,,$(IMAGE_PYTHON)) \
	$(foreach v,$(shell seq $(IMAGE_GLIBC) -1 17),--platform manylinux_2_$(v)_x86_64) \
	--platform manylinux2014_x86_64 --platform manylinux2010_x86_64 --platform manylinux1_x86_64
IMAGE_BUILD_ARGS := --build-arg PYTHON=python$(IMAGE_PYTHON) --build-arg TORCH_BUILD=$(TORCH_BUILD) \
	$(if $(BASE_IMAGE),--build-arg BASE_IMAGE=$(BASE_IMAGE)) \
	$(if $(OFFLINE),--build-arg WHEELHOUSE=$(WHEELHOUSE) --network none)
# The image test's tools (podman, and mmdebstrap for its base), installed when missing (as root).
PODMAN_INSTALL := apt-get update && apt-get install -y podman buildah runc mmdebstrap

.PHONY: demo test check lint web browser netns bench gpu-check clean wheelhouse image podman image-test

$(STAMP): pyproject.toml setup.py rangeret/inference/csrc/knn_vote.c rangeret/inference/csrc/knn_vote_body.h
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -qq --upgrade pip
	$(BIN)/python -m pip install -qq "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -qq -e '.[all,dev]'
	touch $(STAMP)

$(WEB_STAMP): $(WEB)/package.json $(WEB)/package-lock.json
	@command -v npm >/dev/null 2>&1 || { echo "The web page needs Node.js 20 or later with npm; install it, then run make again." >&2; exit 1; }
	cd $(WEB) && npm ci --ignore-scripts --no-audit --no-fund
	touch $(WEB_STAMP)

web: $(WEB_STAMP)

# The browser tests drive Debian's chromium; it is installed here when missing (as root).
browser:
	@command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then $(CHROMIUM_INSTALL); \
	  else echo "The browser tests need chromium: run  sudo sh -c '$(CHROMIUM_INSTALL)'" >&2; exit 1; fi; }

demo: $(STAMP) $(WEB_STAMP)
	$(BIN)/rangeret demo --out $(OUT)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# The ROS 2 tests bring up loopback in their own network namespace with iproute2's `ip`.
netns:
	@command -v ip >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then $(IPROUTE_INSTALL); \
	  else echo "The ROS 2 tests need iproute2: run  sudo sh -c '$(IPROUTE_INSTALL)'" >&2; exit 1; fi; }

test: lint $(WEB_STAMP) browser netns
	$(BIN)/python -m pytest

# The slow tests (Ray clusters, the browser, whole runs) are left out, and with them the browser.
check: lint $(WEB_STAMP) netns
	$(BIN)/python -m pytest -m "not slow"

wheelhouse: $(STAMP)
	rm -rf deploy/wheelhouse/$(WHEELHOUSE)
	$(BIN)/python -m pip download -q --dest deploy/wheelhouse/$(WHEELHOUSE) $(IMAGE_WHEELS) \
	    $(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX)) -c deploy/constraints.txt torch
	$(BIN)/python -m pip download -q --dest deploy/wheelhouse/$(WHEELHOUSE) $(IMAGE_WHEELS) \
	    -c deploy/constraints.txt -r deploy/requirements.txt "setuptools>=68" wheel

image: $(WEB_STAMP)
	@test -n "$(CONTAINER)" || { echo "make image needs docker or podman whose 'info' succeeds (CONTAINER=podman chooses one)" >&2; exit 1; }
	$(CONTAINER) build -f deploy/Dockerfile $(IMAGE_BUILD_ARGS) \
	    $(if $(filter podman,$(notdir $(CONTAINER))),--format docker) -t $(IMAGE) .

podman:
	@command -v podman >/dev/null 2>&1 && command -v mmdebstrap >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then $(PODMAN_INSTALL); \
	  else echo "The image test needs podman and mmdebstrap: run  sudo sh -c '$(PODMAN_INSTALL)'" >&2; exit 1; fi; }

# The CPU image built offline on a base made here, and run as the manifests run it (minutes; not
# part of `make test`): tests/image/run.py.
image-test: $(STAMP) $(WEB_STAMP) podman
	$(BIN)/python -m tests.image.run

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

# Every GPU path in one run of under 5 minutes (benchmarks/gpu_check.py; --smoke runs it on the CPU).
gpu-check: $(STAMP)
	PYTHONPATH=. $(BIN)/python benchmarks/gpu_check.py --out runs/gpu-check

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache $(WEB)/node_modules

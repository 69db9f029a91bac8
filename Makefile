# The two commands of the quick start: `make demo` (the main job) and `make test` (the whole suite).
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

.PHONY: demo test lint web browser netns bench gpu-check clean

$(STAMP): pyproject.toml
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

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

# Every GPU path in one run of under 5 minutes (benchmarks/gpu_check.py; --smoke runs it on the CPU).
gpu-check: $(STAMP)
	PYTHONPATH=. $(BIN)/python benchmarks/gpu_check.py --out runs/gpu-check

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache $(WEB)/node_modules

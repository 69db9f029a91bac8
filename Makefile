# The two commands of the quick start: `make demo` (the main job) and `make test` (the whole suite).
# Both build the virtual environment in .venv on first use.

PYTHON ?= python3
# The CPU build of torch found on this machine kind; on a GPU machine pass e.g. TORCH_SPEC=torch==2.13.0
# with your CUDA wheel index, or install torch into .venv yourself first.
TORCH_SPEC ?= torch==2.13.0
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= runs/demo

.PHONY: demo test lint bench gpu-check clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -qq --upgrade pip
	$(BIN)/python -m pip install -qq "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -qq -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/rangeret demo --out $(OUT)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/python -m pytest

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

# Every GPU path in one run of under 5 minutes (benchmarks/gpu_check.py; --smoke runs it on the CPU).
gpu-check: $(STAMP)
	PYTHONPATH=. $(BIN)/python benchmarks/gpu_check.py --out runs/gpu-check

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache

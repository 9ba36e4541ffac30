# Two commands on a fresh machine: `make demo` (install + fit the built-in quadruped) and `make test`.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# torch==2.13.0 resolves to a local CPU wheel here; a plain `torch` would pull GBs of CUDA packages.
TORCH ?= torch==2.13.0
BPY ?= bpy==5.0.1

.PHONY: install install-test demo test bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

install: $(BIN)/python
	$(BIN)/pip install -q $(TORCH)
	$(BIN)/pip install -q -e .

install-test: $(BIN)/python
	$(BIN)/pip install -q $(TORCH)
	$(BIN)/pip install -q -e ".[test]"
	@# Blender as a module for the `dcc` tests; --no-deps because bpy pins numpy<2 (it runs with numpy 2).
	@# Optional: when it cannot be installed the dcc tests skip with a message.
	-$(BIN)/pip install -q --no-deps $(BPY) zstandard requests || echo "bpy not installed: the dcc tests will skip"

demo: install
	$(BIN)/s3o-fit $(ARGS)

test: install-test
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)

bench: install
	$(BIN)/python scripts/bench_kernels.py --device cpu

clean:
	rm -rf $(VENV) build *.egg-info

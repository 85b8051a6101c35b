# The whole set-up on a fresh machine is `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# torch first, pinned, so that installing the package keeps it. Which build pip gets depends on its set-up: where
# pip is set up with CPU wheels (a find-links folder or an index of them), the CPU wheel; from the public index on
# Linux, the CUDA build (a few GB with its NVIDIA libraries; it runs on a CPU too). TORCH_INDEX takes torch, and only
# torch, from another index: `make install TORCH_INDEX=https://download.pytorch.org/whl/cpu` for the CPU wheel (into
# a new .venv: `make clean` first). Empty, the default: pip's own set-up.
TORCH_PIN ?= torch==2.13.0
TORCH_INDEX ?=

.PHONY: install demo test test-slow test-all lint type bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(STAMP): $(PY) setup.cfg pyproject.toml
	$(PY) -m pip install -q $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX) )"$(TORCH_PIN)"
	$(PY) -m pip install -q -e ".[test,extra]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(PY) -m sb3_poplin.demo

test: $(STAMP)
	$(PY) -m pytest

test-slow: $(STAMP)
	$(PY) -m pytest -m slow

test-all: $(STAMP)
	$(PY) -m pytest -m ""

lint: $(STAMP)
	$(PY) -m ruff check sb3_poplin tests benchmarks

type: $(STAMP)
	$(PY) -m mypy sb3_poplin

clean:
	rm -rf $(VENV) *.egg-info demo_output

# morphgs developer commands. `make help` lists them.
.DEFAULT_GOAL := help
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
EXTRAS ?= test,reference,video,ray,curate

.PHONY: help
help: ## list the targets
	@grep -hE '^[a-zA-Z_-]+:.*?## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*?## "}; {printf "  \033[36m%-12s\033[0m %s\n", $$1, $$2}'

$(VENV)/.deps: pyproject.toml
	python3 -m venv $(VENV)
	$(PIP) install --upgrade pip
	$(PIP) install "maturin>=1.7,<2" numpy
	$(PIP) install $$($(PY) -c "import tomllib;d=tomllib.load(open('pyproject.toml','rb'))['project']['optional-dependencies'];print(' '.join(repr(x) for e in '$(EXTRAS)'.split(',') for x in d[e]))" | tr -d "'")
	touch $@

.PHONY: setup
setup: $(VENV)/.deps ## create .venv with every dependency and build morphgs (release) into it
	VIRTUAL_ENV=$(abspath $(VENV)) PATH=$(abspath $(VENV))/bin:$$PATH maturin develop --release

.PHONY: demo
demo: setup ## the main job: curate clean/corrupted pairs from the built-in sample scenes into out/demo
	$(VENV)/bin/morphgs curate --out out/demo
	$(VENV)/bin/morphgs preview out/demo

.PHONY: lint
lint: ## rustfmt and clippy (warnings are errors)
	cargo fmt --all --check
	cargo clippy --workspace --all-targets --release -- -D warnings

.PHONY: test
test: setup lint ## everything CI runs: lint, cargo tests, stub check, pytest
	cargo test --workspace --release
	$(PY) -m mypy.stubtest morphgs._core --allowlist stubtest-allowlist.txt
	$(PY) -m pytest -q

.PHONY: bench
bench: setup ## criterion benches and the side-by-side Python benchmarks
	cargo bench --workspace
	for b in benches/*.py; do $(PY) $$b; done

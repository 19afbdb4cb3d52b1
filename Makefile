# morphgs developer commands. `make help` lists them.
.DEFAULT_GOAL := help
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
# Each target installs only the extras (pyproject's [project.optional-dependencies]) it uses.
DEMO_EXTRAS ?= curate,video
TEST_EXTRAS ?= test,reference,video,ray,curate,fit
BENCH_EXTRAS ?= $(TEST_EXTRAS)

.PHONY: help
help: ## list the targets
	@grep -hE '^[a-zA-Z_-]+:.*?## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*?## "}; {printf "  \033[36m%-12s\033[0m %s\n", $$1, $$2}'

$(VENV)/.base:
	python3 -m venv $(VENV)
	$(PIP) install --upgrade pip
	$(PIP) install "maturin>=1.7,<2" numpy
	touch $@

# install the named extras' requirements (pip skips what is already there); one stamp per set
$(VENV)/.extras-%: pyproject.toml $(VENV)/.base
	$(PIP) install $$($(PY) -c "import tomllib,sys;d=tomllib.load(open('pyproject.toml','rb'))['project']['optional-dependencies'];print(' '.join(repr(x) for e in sys.argv[1].split(',') for x in d[e]))" '$*' | tr -d "'")
	touch $@

# build morphgs (release) into the venv
.PHONY: build
build: $(VENV)/.base
	VIRTUAL_ENV=$(abspath $(VENV)) PATH=$(abspath $(VENV))/bin:$$PATH maturin develop --release

.PHONY: setup
setup: $(VENV)/.extras-$(TEST_EXTRAS) build ## create .venv with every test dependency and build morphgs (release) into it

.PHONY: demo
demo: $(VENV)/.extras-$(DEMO_EXTRAS) build ## the main job: curate clean/corrupted pairs from the built-in sample scenes into out/demo
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
bench: $(VENV)/.extras-$(BENCH_EXTRAS) build ## criterion benches and the side-by-side Python benchmarks
	cargo bench --workspace
	for b in benches/*.py; do $(PY) $$b; done

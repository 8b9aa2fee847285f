# rayaccel: `make demo` sets everything up and runs the main job; `make test` runs the suite.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
SHARED_SCENES := $(abspath ../shared/scenes)
OUT := out
DEMO_SCENE := teapot
# The default builder and traversal, and the fastest traversal (docs/performance.md).
DEMO_BUILDER := bvh2.binned_sah
DEMO_TRAVERSALS := bvh2.stack bvh2.wide

# Tests and benchmarks find the bundled scenes through this search path when present.
ifneq ($(wildcard $(SHARED_SCENES)),)
export RAYACCEL_SCENE_PATH ?= $(SHARED_SCENES)
endif

.PHONY: demo test bench lint docs system-deps clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,peers,study,gpu]"
	touch $(STAMP)

# Open3D's wheel needs Debian's libusb-1.0-0; install it when we may (root with apt-get).
system-deps:
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0.so.0; then \
	  if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	    (apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1)) \
	    || echo "note: could not install libusb-1.0-0; the Open3D peer will be skipped"; \
	  else echo "note: libusb-1.0-0 missing; the Open3D peer will be skipped"; fi; \
	fi

demo: $(STAMP) system-deps
	mkdir -p $(OUT)
	$(BIN)/rayaccel list
	$(BIN)/rayaccel bench $(DEMO_SCENE) --accel $(DEMO_BUILDER) --traversal $(DEMO_TRAVERSALS) \
	  --rays primary,diffuse,shadow --threads 2 --json $(OUT)/demo-bench.jsonl
	$(BIN)/rayaccel render $(DEMO_SCENE) --accel $(DEMO_BUILDER) --view heatmap \
	  --metric nodes -o $(OUT)/demo-heatmap.png --legend $(OUT)/demo-legend.png
	$(BIN)/rayaccel render $(DEMO_SCENE) --accel $(DEMO_BUILDER) --view shade -o $(OUT)/demo-shade.png
	@echo "demo outputs in $(OUT)/"

# Kernels compile on every core first (`rayaccel cache warm`: the serial kernels and the
# parallel ones plain queries reach, all the default tier runs); the suite then loads them,
# one pytest-xdist worker per core, each test file on one worker (its fixtures built once),
# the files in the order tests/conftest.py gives them (the longest first).
test: $(STAMP) system-deps
	$(BIN)/rayaccel cache warm --quiet --common-parallel
	$(BIN)/python -m pytest -q -n auto --dist loadfile --no-loadscope-reorder

bench: $(STAMP) system-deps
	$(BIN)/python benchmarks/bench_core.py --threads 2

# ruff (style, docstrings) on everything; mypy on src/rayaccel ([tool.mypy] in pyproject.toml).
lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/mypy

# The documentation (Sphinx, pydata theme, numpydoc, gallery of examples/) into docs/_build/html.
DOCS_STAMP := $(VENV)/.docs-stamp

$(DOCS_STAMP): $(STAMP) pyproject.toml
	$(BIN)/python -m pip install --quiet -e ".[docs]"
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	$(BIN)/sphinx-build -W --keep-going -b html docs docs/_build/html
	@echo "documentation in docs/_build/html/index.html"

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .hypothesis .mypy_cache docs/_build docs/auto_examples docs/gen_modules \
	  docs/sg_execution_times.rst
	find src -name __pycache__ -type d -prune -exec rm -rf {} +

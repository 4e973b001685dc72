# mslam — every install step lives here so a fresh machine (and CI) needs only `make`.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
MSLAM := $(VENV)/bin/mslam
DEMO_DIR ?= results/demo
PYTEST_ARGS ?=
# `make test` spreads the tests over this many processes (pytest-xdist): on the 2-core CI machines 1.65x faster than
# one (6 min 23 s -> 3 min 52 s on an AVX512-BF16 EPYC); 1 = in this process, as `make test-all` runs.
TEST_WORKERS ?= 2

.PHONY: install demo test test-all bench gpu-check lint typecheck clean weights book book-smoke redkitchen-whole redkitchen-reentries

install: $(VENV)/.installed

# open3d-cpu needs libusb-1.0 at import time; install it from apt when missing.
# The CPU torch wheel is installed first and pinned so nothing pulls a CUDA build.
$(VENV)/.installed: pyproject.toml
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  echo "installing libusb-1.0-0 (needed by open3d)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP) install -q --disable-pip-version-check "torch==2.13.0" || \
	  $(PIP) install -q --disable-pip-version-check "torch>=2.5,<2.14"
	$(PIP) install -q --disable-pip-version-check "torch>=2.5,<2.14" -e ".[test,dask]"
	touch $@

# The main job on the built-in default: a synthetic room sequence, the default model,
# the paper's scheme (replay+ewc) with our VO front end, then the paper-style report.
demo: install
	$(MSLAM) synth $(DEMO_DIR)/data/room --scene room --frames 150 --size 640x480 --seed 0
	$(MSLAM) run $(DEMO_DIR)/data/room --out $(DEMO_DIR) --force
	$(MSLAM) report $(DEMO_DIR) --out $(DEMO_DIR)/report

# CI: lint and type check, then everything but `slow` (tests marked `data` run when ../shared/data exists, else
# skip); the docstrings' examples run as tests too (tests/test_doctests.py).
test: install lint typecheck
	$(PY) -m pytest -q -m "not slow and not gpu" $(if $(filter-out 1,$(TEST_WORKERS)),-n $(TEST_WORKERS)) $(PYTEST_ARGS)

test-all: install
	$(PY) -m pytest -q $(PYTEST_ARGS)

bench: install
	$(MSLAM) bench suite --memory --whole-run --grid

# The CUDA path against the CPU on a machine with an NVIDIA GPU (≤ 5 min): step and prediction times,
# a 100-frame shared window on cuda and on cpu (same keyframes, PCD within 1 point). Skips without CUDA.
gpu-check: install
	$(MSLAM) bench gpu-check

# The results book (configs/book.yaml): every experiment the README reports, resumable (run it again after a kill),
# then results/book/ and, with --publish, results/book.json (committed) and the README's blocks rendered from it.
# Hours on 2 cores; BOOK_ARGS adds options (--only table3, --executor dask --scheduler ADDR, ...).
BOOK ?= configs/book.yaml
BOOK_ARGS ?= -j 2
book: install
	$(MSLAM) book $(BOOK) $(BOOK_ARGS) --publish

# The book's machinery in a minute, on rendered rooms (what CI's tests/book run).
book-smoke: install
	$(MSLAM) book configs/book_smoke.yaml --out results/book_smoke

# RedKitchen whole (the registry's redkitchen_whole, a sequence of the results book): the 1000-frame block assembled
# from the two RedKitchen windows of the shared data by links, with the first window's depth (PCD is scored there).
SHARED_DATA ?= ../shared/data
RKW := _built/redkitchen_whole
redkitchen-whole:
	@test -x $(SHARED_DATA)/redkitchen_whole.sh || { echo "redkitchen-whole: $(SHARED_DATA)/redkitchen_whole.sh not found (set SHARED_DATA=...)"; exit 1; }
	rm -rf $(RKW).tmp && $(SHARED_DATA)/redkitchen_whole.sh $(RKW).tmp
	cp $(SHARED_DATA)/redkitchen_7scenes/depth.txt $(RKW).tmp/
	ln -s "$$(cd $(SHARED_DATA)/redkitchen_7scenes && pwd)/depth" $(RKW).tmp/depth
	rm -rf $(RKW) && mv $(RKW).tmp $(RKW)

# Re-entry sequences of real images for relocalisation and map merging (the registry's redkitchen_cut and
# redkitchen_kidnap), spliced from redkitchen_whole by links: the cut drops frames 450-629 (the camera jumps 1.42 m and
# 27 degrees, onto a place it saw before the cut); the kidnap plays frames 400-839, then 140-399 (a jump of 0.51 m and
# 97 degrees, onto a place the first part saw). Ranges chosen from the GT; tests/datasets/test_splice.py reads them here.
RK_CUT_KEEP := --keep 0:450 --keep 630:1000
RK_KIDNAP_KEEP := --keep 400:840 --keep 140:400
redkitchen-reentries: install
	@test -f $(RKW)/rgb.txt || { echo "redkitchen-reentries: $(RKW) not found; run 'make redkitchen-whole' first"; exit 1; }
	$(MSLAM) datasets splice $(RKW) _built/redkitchen_cut $(RK_CUT_KEEP)
	$(MSLAM) datasets splice $(RKW) _built/redkitchen_kidnap $(RK_KIDNAP_KEEP)

weights: install
	$(MSLAM) pretrain

# The rule set lives in pyproject.toml ([tool.ruff.lint]); a finding fails the target (and `make test`).
lint: install
	$(PY) -m ruff check mutualslam_cli tests

# mypy over the files pyproject.toml's [tool.mypy] names (the whole package).
typecheck: install
	$(PY) -m mypy

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info

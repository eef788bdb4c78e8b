# loopmodel — the README's two commands: `make demo` and `make test`.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SHARED ?= ../shared

.PHONY: demo test test-fast setup syslibs viewer-libs lint bench clean

# The numba kernels compiled into numba's cache, one process per core (python -m loopmodel.kernels).
setup: syslibs $(STAMP)
	@$(PY) -m loopmodel.kernels

# open3d 0.20 fails to import without Debian's libusb-1.0-0.
syslibs:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing libusb-1.0-0 (needed by open3d)"; \
	    (apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null)) || \
	     { echo "error: could not install Debian package libusb-1.0-0 (needed by open3d)"; exit 1; }; \
	  else \
	    echo "error: open3d needs the Debian package libusb-1.0-0; install it: sudo apt-get install libusb-1.0-0"; exit 1; \
	  fi; \
	fi
	@# the back end's worker process runs on jemalloc when it is installed (backend.worker_allocator; optional)
	@if ! ldconfig -p 2>/dev/null | grep -q 'libjemalloc.so.2'; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing libjemalloc2 (the back-end worker's allocator)"; \
	    (apt-get install -y -q libjemalloc2 >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null && apt-get install -y -q libjemalloc2 >/dev/null)) || \
	     echo "note: could not install libjemalloc2: the back-end worker uses the system allocator"; \
	  else \
	    echo "note: the back-end worker is faster on jemalloc: sudo apt-get install libjemalloc2"; \
	  fi; \
	fi

# Headless rerun screenshots (tools/screenshot_rerun.sh, tests/test_viz.py): a virtual X server
# and Mesa's CPU Vulkan driver. Optional: the test is skipped without them.
viewer-libs:
	@if ! command -v xvfb-run >/dev/null || ! ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    (apt-get install -y -q xvfb mesa-vulkan-drivers >/dev/null 2>&1 || \
	     (apt-get update -q >/dev/null && apt-get install -y -q xvfb mesa-vulkan-drivers >/dev/null)); \
	  else \
	    echo "note: headless rerun screenshots need: sudo apt-get install xvfb mesa-vulkan-drivers"; \
	  fi; \
	fi

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@# uv (from PyPI) installs the releases pip would choose (checked: the same versions of all 121 packages)
	@# in 22 s on a fresh clone against pip's ~150 s (2026-12-04, quiet); pip when uv cannot be had.
	$(PY) -m pip install -qq uv && $(VENV)/bin/uv pip install -q --python $(PY) -e '.[dev,viz,batch]' || \
	  { $(PY) -m pip install -q --upgrade pip && $(PY) -m pip install -q -e '.[dev,viz,batch]'; }
	@touch $(STAMP)

# The demo compiles only the kernels its run calls (configs/sim.yaml: not SURF, the Givens estimator, the
# KLT share), beside the sample's generation (tools/demo.sh); `make setup` / `make test` compile the rest.
demo: syslibs $(STAMP)
	@bash tools/demo.sh

# Two test processes (pytest-xdist), one per core of the 2-core machine; a module's tests stay in one
# process (its module fixtures are built once).
test: setup viewer-libs
	$(PY) -m pytest -q -x -n 2 --dist loadfile --durations=15

# Development tier: everything not marked slow (CI still runs the whole suite).
test-fast: setup
	$(PY) -m pytest -q -x -n 2 --dist loadfile -m "not slow"

lint: setup
	$(VENV)/bin/ruff check loopmodel tests tools
	$(VENV)/bin/mypy loopmodel

clean:
	rm -rf $(VENV) results build *.egg-info

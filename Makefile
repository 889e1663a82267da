# projo4d: every target does its own set-up on a fresh Debian machine with Python 3.11.
#   make demo   install, then run the main job on an embedded synthetic scene
#   make test   install, then run the test suite
#   make docs   install, then build the documentation site (warnings are errors)
SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.projo4d-installed
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
DEMO_OUT ?= outputs/demo
TORCH_INDEX ?=
TORCH_PIP_ARGS := $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX),)

.PHONY: demo test docs install sysdeps clean constraints

install: $(STAMP)

# The browser viewer's test loads the page in headless Chromium; install it from Debian when it is
# missing (about 20 s; `make test` only). Nothing else needs system packages (open3d is an optional extra).
sysdeps:
	@if ! command -v chromium >/dev/null 2>&1; then \
	  echo "installing Debian package chromium (headless browser for tests/test_twin_viewer.py)"; \
	  $(SUDO) apt-get install -y -q chromium || { $(SUDO) apt-get update -q && $(SUDO) apt-get install -y -q chromium; } \
	    || echo "chromium could not be installed: the browser test will be skipped"; \
	fi

$(STAMP): pyproject.toml constraints.txt
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	# torch first, at the version constraints.txt pins, so that nothing later pulls a CUDA build
	$(BIN)/python -m pip install -q $(TORCH_PIP_ARGS) -c constraints.txt torch
	# pyproject.toml declares compatible ranges; constraints.txt is the exact set CI tests
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[test,docs,viewer]'
	@touch $(STAMP)

test: install sysdeps
	$(BIN)/python -m pytest -q -n 2 --dist loadgroup

demo: install
	$(BIN)/projo4d demo --out $(DEMO_OUT)

docs: install
	$(BIN)/python -m sphinx -W --keep-going -b html docs docs/_build/html

# Re-pin constraints.txt to what .venv holds now (after deliberately upgrading a package there).
constraints:
	@{ echo "# The exact package set CI tests (make install passes -c constraints.txt to every pip install)."; \
	   echo "# pyproject.toml declares the compatible ranges. Regenerate with: make constraints"; \
	   echo "# torch is the CPU build here (2.13.0+cpu); '==2.13.0' also accepts a CUDA build of the same release."; \
	   $(BIN)/python -m pip list --format=freeze --exclude-editable \
	     | grep -viE '^(pip|setuptools|wheel)==' | sed -E 's/^(torch==[^+]*)\+.*/\1/'; } > constraints.txt

clean:
	rm -rf .warp_cache .pytest_cache docs/_build outputs

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

.PHONY: demo test docs install sysdeps clean

install: $(STAMP)

# open3d's wheel links against libusb-1.0; install it from Debian when it is missing.
sysdeps:
	@if ! /sbin/ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  echo "installing Debian package libusb-1.0-0 (needed by open3d)"; \
	  $(SUDO) apt-get install -y -q libusb-1.0-0 || { $(SUDO) apt-get update -q && $(SUDO) apt-get install -y -q libusb-1.0-0; }; \
	fi

$(STAMP): pyproject.toml | sysdeps
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	# torch first, pinned, so that nothing later pulls a CUDA build
	$(BIN)/python -m pip install -q $(TORCH_PIP_ARGS) torch==2.13.0
	$(BIN)/python -m pip install -q -e '.[test,docs]'
	@touch $(STAMP)

test: install
	$(BIN)/python -m pytest -q -n 2 --dist loadgroup

demo: install
	$(BIN)/projo4d demo --out $(DEMO_OUT)

docs: install
	$(BIN)/python -m sphinx -W --keep-going -b html docs docs/_build/html

clean:
	rm -rf .warp_cache .pytest_cache docs/_build outputs

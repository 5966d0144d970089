# treetraits: `make demo` and `make test` set up whatever is missing, then run.
# Setup is idempotent: system packages are checked with dpkg and installed only when
# missing (as root, or through sudo); the virtualenv is rebuilt only when pyproject.toml
# changes.

SHELL := /bin/bash
.DEFAULT_GOAL := help

# The first Python >= 3.10 on PATH (override: make test PYTHON=/usr/bin/python3.12).
PYTHON ?= $(shell for p in python3.13 python3.12 python3.11 python3.10 python3; do \
	command -v $$p >/dev/null 2>&1 && $$p -c 'import sys; sys.exit(sys.version_info < (3, 10))' \
	2>/dev/null && { echo $$p; break; }; done)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT := out/demo

# Runtime libraries the wheels load (libusb for pyusb, libGL/libEGL/libgomp for open3d and
# OpenCV) and what building systemd-python needs (libsystemd headers, pkg-config, a C
# compiler and the Python headers).
SYSTEM_PACKAGES := libusb-1.0-0 libgl1 libegl1 libgomp1 libsystemd-dev pkg-config gcc systemd
# Only for `make test`: tests/season/test_batch.py renders the HTML report in a real browser.
# Best effort: where the package is not in apt (Ubuntu's Chromium is a snap) the test
# that needs it is skipped with its reason.
TEST_PACKAGES := chromium

.PHONY: help setup system-packages kernels demo test lint bench clean install uninstall

help:
	@echo "make demo    set up, then simulate a drive through the orchard twin and replay it"
	@echo "make test    set up, then run the whole test suite and the linter"
	@echo "make bench   run the benchmarks in bench/"
	@echo "make clean   remove the virtualenv and outputs"
	@echo "make install install the onboard service (as root; DESTDIR=, PREFIX= to stage)"
	@echo "make uninstall  remove it (keeps the config, the data and the user)"

setup: system-packages $(STAMP) kernels

# The compiled kernels (numba) into their cache beside the sources, as `make install` does
# for the service (systemd/install.sh): ~30 s the first time or after a kernel's source
# changed, 1 s when they are there. Every process after it loads them instead of
# compiling: the test suite's workers and the commands its tests run.
kernels: $(STAMP)
	@$(BIN)/python -c 'from treetraits.service.runtime import load_pipeline; load_pipeline()'

system-packages:
	@if [ -z "$(PYTHON)" ]; then \
		echo "error: treetraits needs Python >= 3.10 (see README: 'Putting it on a robot')" >&2; \
		exit 1; \
	fi
	@if ! command -v dpkg-query >/dev/null 2>&1; then \
		echo "note: not a Debian/Ubuntu system; make sure these are installed: $(SYSTEM_PACKAGES)"; \
		exit 0; \
	fi; \
	ver=$$($(PYTHON) -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")'); \
	wanted="$(SYSTEM_PACKAGES)"; \
	$(PYTHON) -c 'import ensurepip, venv' 2>/dev/null || wanted="$$wanted python$$ver-venv"; \
	$(PYTHON) -c 'import sysconfig, os, sys; \
		sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
		|| wanted="$$wanted python$$ver-dev"; \
	missing=""; \
	for p in $$wanted; do \
		dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
		if [ "$$(id -u)" = 0 ]; then sudo=""; \
		elif command -v sudo >/dev/null 2>&1; then sudo="sudo"; \
		else echo "error: need root or sudo to install:$$missing" >&2; exit 1; fi; \
		echo "installing system packages:$$missing"; \
		$$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $$missing \
		|| { $$sudo apt-get update -q && \
		     $$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $$missing; }; \
	fi; \
	extra=""; \
	for p in $(EXTRA_PACKAGES); do \
		dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || extra="$$extra $$p"; \
	done; \
	if [ -n "$$extra" ]; then \
		sudo=""; [ "$$(id -u)" = 0 ] || sudo="sudo"; \
		echo "installing test packages:$$extra"; \
		$$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $$extra \
		|| { $$sudo apt-get update -q && \
		     $$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $$extra; } \
		|| echo "note: could not install$$extra (Ubuntu ships Chromium as a snap): the tests that need it say so and are skipped"; \
	fi

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[all,test]'
	@touch $(STAMP)

demo: setup
	@# --force: a rerun replaces the previous demo's recording and outputs (docs/cli.md).
	$(BIN)/treetraits sim --grid 5x5 --path straight --seed 0 --out $(DEMO_OUT)/survey.mcap --force
	$(BIN)/treetraits replay $(DEMO_OUT)/survey.mcap --out $(DEMO_OUT) --force

# The suite on every core (pytest-xdist; a module stays on one worker, --dist loadfile, so
# its fixtures are built once; tests/conftest.py hands out the longest modules first), then
# the tests that hold a wall-clock rate or deadline (marker `realtime`: the Jackal teleop
# relay's 50 Hz, the camera's frame latency) alone: beside a worker keeping the other core
# busy the teleop relay's test failed once in four runs. TEST_WORKERS=0: one process.
TEST_WORKERS ?= auto

test: EXTRA_PACKAGES := $(TEST_PACKAGES)
test: setup
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile -m "not realtime"
	$(BIN)/python -m pytest -m realtime

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

bench: setup
	$(BIN)/python bench/decode.py

clean:
	rm -rf $(VENV) out *.egg-info

# The onboard service: venv in PREFIX (/opt/treetraits), unit, udev rules, sysctl, default
# config; see docs/deployment.md. DESTDIR stages into a directory without touching the system.
install:
	DESTDIR="$(DESTDIR)" PREFIX="$(or $(PREFIX),/opt/treetraits)" PYTHON="$(PYTHON)" systemd/install.sh $(INSTALL_FLAGS)

uninstall:
	DESTDIR="$(DESTDIR)" PREFIX="$(or $(PREFIX),/opt/treetraits)" systemd/install.sh --uninstall

# One-command set-up: `make demo` runs the main job, `make test` runs the whole suite.
# Both create .venv/ (Python 3.11) and install everything they need when missing.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.gft_odom_installed
DEMO_OUT ?= demo_out
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: setup demo test test-fast lint bench bench-record clean system-deps

setup: system-deps $(STAMP)

# open3d needs libusb-1.0 (and libgomp) at import time; install them from apt when missing.
system-deps:
	@if ! ldconfig -p | grep -q 'libusb-1.0.so.0' || ! ldconfig -p | grep -q 'libgomp.so.1'; then \
		echo 'installing system packages for open3d: libusb-1.0-0 libgomp1'; \
		$(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libusb-1.0-0 libgomp1; \
	fi

$(STAMP): setup.py requirements-ros.txt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements-ros.txt -e '.[test]'
	@touch $(STAMP)

demo: setup
	$(VENV)/bin/gft-odom demo --out $(DEMO_OUT)

test: setup
	$(PY) -m pytest -q

test-fast: setup
	$(PY) -m pytest -q -m 'not slow'

lint: setup
	$(VENV)/bin/ruff check gft_odom test benchmarks

# Every benchmark, the record included (several hours on 2 cores; see docs/benchmarks.md).
bench: setup
	$(PY) benchmarks/run_all.py

# Only the benchmark of record: its ten varied drives, the four never used, the twenty
# edge-of-block drives and the six of the stress family (6 km), gft_odom and seven peers.
# Simulates the drives once into ~/.cache/gft_odom/drives, then runs every method on them
# (many hours on 2 cores; each result is cached, so a run can be resumed).
bench-record: setup
	$(PY) benchmarks/bench_record.py --drives record
	$(PY) benchmarks/bench_record.py --drives never-used
	$(PY) benchmarks/bench_record.py --drives edge
	$(PY) benchmarks/bench_record.py --drives stress

clean:
	rm -rf build install log $(DEMO_OUT) .pytest_cache

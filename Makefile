# The two set-up commands (see README): `make demo` and `make test`.
# Each creates or refreshes the virtual environment in .venv/ and installs nrpose there.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

BLENDER_VENV := .venv-blender

.PHONY: venv pocl pypi-pocl demo test bench blender fuzz
venv:
	@test -x $(PY) || { $(PYTHON) -m venv $(VENV) && $(PY) -m pip install --quiet --disable-pip-version-check --upgrade pip; }
	@$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test,bench,ray]'

# PyPI's PoCL 3.0 compiles with LLVM 14, which does not know newer processors (AMD Zen 5 among
# them): where it cannot build a kernel, Debian's PoCL (LLVM 15) is installed beside it as root,
# and nrpose passes over the one that cannot; elsewhere nrpose's error says what to install.
pocl: venv
	@$(MAKE) -s pypi-pocl 2>/dev/null || test -f /etc/OpenCL/vendors/pocl.icd || \
	{ test "$$(id -u)" = 0 && command -v apt-get >/dev/null && apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq pocl-opencl-icd >/dev/null; } || \
	echo "make: PyPI's PoCL cannot compile for this CPU; install a newer PoCL (apt install pocl-opencl-icd)" >&2

# exit status 0 where PyPI's PoCL, seen alone, builds a kernel on this CPU (after venv)
pypi-pocl:
	@$(PY) -c 'import sys; from nrpose.diagnostics import pypi_pocl_refusal; sys.exit(pypi_pocl_refusal() is not None)'

demo: venv pocl
	$(VENV)/bin/nrpose demo

test: venv pocl
	$(PY) -m pytest -q --ignore=tests/test_fuzz.py
	# the fuzz cases fork from a process that has no OpenCL context yet: a pytest of their own
	$(PY) -m pytest -q tests/test_fuzz.py

bench: venv
	$(PY) -m bench --suite all

# The long fuzz run of the command line (tests/test_fuzz.py is the bounded CI run): reproducers in fuzz-repro/
FUZZ_MINUTES ?= 30
fuzz: venv
	$(PY) bench/fuzz.py --workers 2 --minutes $(FUZZ_MINUTES) --shared --out bench/results/fuzz.json --repro fuzz-repro

# Blender 5 (bpy) in its own environment: a test client for glTF outputs and the e2e benchmark's anchor
blender:
	@test -x $(BLENDER_VENV)/bin/python || $(PYTHON) -m venv $(BLENDER_VENV)
	@$(BLENDER_VENV)/bin/python -m pip install --quiet --disable-pip-version-check 'bpy>=5,<6' numpy

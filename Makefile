# The two set-up commands (see README): `make demo` and `make test`.
# Each creates or refreshes the virtual environment in .venv/ and installs nrpose there.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

BLENDER_VENV := .venv-blender

.PHONY: venv demo test bench blender fuzz
venv:
	@test -x $(PY) || { $(PYTHON) -m venv $(VENV) && $(PY) -m pip install --quiet --disable-pip-version-check --upgrade pip; }
	@$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test,bench,ray]'

demo: venv
	$(VENV)/bin/nrpose demo

test: venv
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

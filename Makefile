# The two set-up commands (see README): `make demo` and `make test`.
# Each creates or refreshes the virtual environment in .venv/ and installs nrpose there.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

BLENDER_VENV := .venv-blender

.PHONY: venv demo test bench blender
venv:
	@test -x $(PY) || { $(PYTHON) -m venv $(VENV) && $(PY) -m pip install --quiet --disable-pip-version-check --upgrade pip; }
	@$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test,bench,ray]'

demo: venv
	$(VENV)/bin/nrpose demo

test: venv
	$(PY) -m pytest -q

bench: venv
	$(PY) -m bench --suite all

# Blender 5 (bpy) in its own environment: a test client for glTF outputs and the e2e benchmark's anchor
blender:
	@test -x $(BLENDER_VENV)/bin/python || $(PYTHON) -m venv $(BLENDER_VENV)
	@$(BLENDER_VENV)/bin/python -m pip install --quiet --disable-pip-version-check 'bpy>=5,<6' numpy

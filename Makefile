# The two set-up commands (see README): `make demo` and `make test`.
# Each creates or refreshes the virtual environment in .venv/ and installs nrpose there.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: venv demo test bench
venv:
	@test -x $(PY) || { $(PYTHON) -m venv $(VENV) && $(PY) -m pip install --quiet --disable-pip-version-check --upgrade pip; }
	@$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test,bench]'

demo: venv
	$(VENV)/bin/nrpose demo

test: venv
	$(PY) -m pytest -q

bench: venv
	$(PY) -m bench --suite all

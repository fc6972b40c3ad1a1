# The two commands of the README:   make demo   (main job)   and   make test   (tests);
# make docs builds the documentation site.
PY ?= python3
VENV ?= .venv
BIN = $(VENV)/bin
SYSTEM ?= van_der_pol

$(BIN)/nlyap: setup.cfg pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt torch==2.13.0
	$(BIN)/python -m pip install -q -c constraints.txt -e ".[dev]"
	touch $(BIN)/nlyap

install: $(BIN)/nlyap

demo: install
	$(BIN)/nlyap run $(SYSTEM) --out runs/$(SYSTEM)

test: install
	$(BIN)/python -m pytest -q -rs

test-slow: install
	$(BIN)/python -m pytest -q -rs -m slow

# the documentation site (docs/_build/html): the venv of `install` plus the docs extra;
# warnings are errors, so a broken reference or a failing example fails the build
docs: $(BIN)/sphinx-build
	$(BIN)/python -m sphinx -W --keep-going -q -b html docs docs/_build/html

$(BIN)/sphinx-build: $(BIN)/nlyap
	$(BIN)/python -m pip install -q -c constraints.txt -e ".[dev,docs]"
	touch $(BIN)/sphinx-build

bench: install
	$(BIN)/python bench/verify.py
	$(BIN)/python bench/compare.py

.PHONY: install demo test test-slow bench docs

# The two commands of the README:   make demo   (main job)   and   make test   (tests).
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

bench: install
	$(BIN)/python bench/verify.py
	$(BIN)/python bench/compare.py

.PHONY: install demo test test-slow bench

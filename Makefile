# The two commands of the README. Each creates the virtual environment (.venv) on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

## The main job on the embedded default scene.
demo: $(STAMP)
	$(BIN)/mnemoslam demo

## The test suite (real-data tests read MNEMOSLAM_DATA, default ../shared/data).
test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python bench/run_sequences.py

clean:
	rm -rf $(VENV) out

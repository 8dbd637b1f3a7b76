# The two commands of the README. Each creates the virtual environment (.venv) on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test check lint typecheck venv browser bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

## The main job on the embedded default scene.
demo: $(STAMP)
	$(BIN)/mnemoslam demo

## Both test targets write Python's bytecode caches (__pycache__, ignored by git and docker) even where
## the environment sets PYTHONDONTWRITEBYTECODE (this one does): the suite starts ~100 Python
## processes (services, their mapping children, CLI runs) that would each compile the package's
## sources again, and each xdist worker would rewrite and compile every test module's asserts again
## (~10 s of its collection). `make check` on the 2-core AVX2 machine (pytest's time): 96 s with the
## caches written by an earlier run, 114 s on a fresh clone (written as it goes), 125 s without.
PYCACHE := PYTHONDONTWRITEBYTECODE=

## The test suite (real-data tests read MNEMOSLAM_DATA, default ../shared/data), on two pytest-xdist
## workers: each test module on one worker, the modules that share the session's runs on the same
## one (tests/conftest.py XDIST_GROUPS); the 15 longest tests are listed at the end (where the
## time goes). TEST_WORKERS=0 runs it in this one process.
TEST_WORKERS ?= 2
test: $(STAMP) browser
	$(PYCACHE) $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=15

## The fast tier for the edit loop: the suite without the tests marked slow (whole sequences,
## long streams through the service, the viewer's browser test: tests/conftest.py SLOW), on the
## same workers. No Chromium.
check: $(STAMP)
	$(PYCACHE) $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not slow"

## The linter (ruff, pinned in the test extras; its rules in pyproject.toml). CI runs it before the tests.
lint: $(STAMP)
	$(BIN)/ruff check .

## The type checker (mypy, pinned in the test extras; its settings in pyproject.toml) on the core
## packages, TYPECHECK; CI runs it after the linter. mypy cannot follow setuptools' editable
## finder, so it reads the code through build/typecheck/mnemoslam/{service,client,storage}, links
## to this checkout's folders (its messages name files by those paths).
TYPECHECK ?= mnemoslam.client.kernel mnemoslam.service.tracking mnemoslam.service.config mnemoslam.storage \
	mnemoslam.service.grid mnemoslam.service.memory mnemoslam.service.mapping
typecheck: $(STAMP)
	mkdir -p build/typecheck/mnemoslam
	for d in service client storage; do ln -sfn "$(CURDIR)/$$d" build/typecheck/mnemoslam/$$d; done
	$(BIN)/mypy --cache-dir build/mypy-cache $(addprefix -p ,$(TYPECHECK))

## Chromium for the viewer's browser test (tests/test_viewer.py): the Debian package, installed
## with apt-get when it is missing and apt-get can (root, or sudo without a password). Not fatal:
## without it that test skips, or fails where browsers are required (MNEMOSLAM_REQUIRE_DATA, CI).
CHROMIUM ?= $(or $(MNEMOSLAM_CHROMIUM),/usr/bin/chromium)
browser:
	@if [ ! -x "$(CHROMIUM)" ] && command -v apt-get >/dev/null 2>&1; then \
		if [ "$$(id -u)" = 0 ]; then sudo=; else sudo="sudo -n"; fi; \
		echo "make: installing chromium (apt-get) for the viewer's browser test"; \
		{ $$sudo apt-get update -qq && $$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; } \
			>/dev/null 2>&1 || echo "make: chromium not installed: the viewer's browser test will skip (fail in CI)"; \
	fi

bench: $(STAMP)
	$(BIN)/python bench/run_sequences.py

clean:
	rm -rf $(VENV) out

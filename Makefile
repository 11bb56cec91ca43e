PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/twin demo

# test_services_live.py (supervised multi-process twin, SIGKILL restart) passes alone and under
# CPU load, but failed beside the other workers' tests: it runs on its own after the parallel run.
test: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -n 2 --dist loadfile -q --ignore=tests/test_services_live.py
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q tests/test_services_live.py

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	@export OPENBLAS_NUM_THREADS=1; for f in benchmarks/*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache

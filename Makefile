PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-seeds lint bench clean browser

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/twin demo

# headless Chromium and its driver for the dashboard's browser test (Debian packages), installed
# when missing and apt-get is usable (root); otherwise that test is skipped and says why
browser:
	@if [ ! -x /usr/bin/chromium ] || [ ! -x /usr/bin/chromedriver ]; then \
		if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
			apt-get install -y -q chromium chromium-driver >/dev/null \
			|| { apt-get update -q >/dev/null && apt-get install -y -q chromium chromium-driver >/dev/null; } \
			|| echo "make: could not install chromium chromium-driver: the browser test is skipped"; \
		else \
			echo "make: chromium or chromedriver missing and apt-get not usable: the browser test is skipped"; \
		fi; \
	fi

test: $(STAMP) browser
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -n 2 --dist loadfile -q

# the DEM trend tests again on other samples of the same physics (other scene seeds)
TEST_SEEDS ?= 1
test-seeds: $(STAMP)
	@for s in $(TEST_SEEDS); do \
		echo "== TWIN_TEST_SEED=$$s"; \
		TWIN_TEST_SEED=$$s OPENBLAS_NUM_THREADS=1 \
			$(BIN)/python -m pytest -n 2 --dist loadfile -q -m dem_trend || exit 1; \
	done

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	@export OPENBLAS_NUM_THREADS=1; for f in benchmarks/*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache

# The two commands a newcomer types: `make run` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DATA := data/sim_office.mcap
OUT ?= runs/sim_office

.PHONY: run test venv benchmark data clean

venv: $(STAMP)

# (re)install when the venv is missing or pyproject.toml changed
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev,peers]"
	$(VENV)/bin/rerun analytics disable >/dev/null 2>&1 || true
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/slam2d run $(DATA) --out $(OUT)
	@echo "outputs in $(OUT): trajectory.txt map.pgm map.yaml map.png config.yaml summary.json"

test: $(STAMP)
	$(PY) -m pytest -q

benchmark: $(STAMP)
	$(PY) tools/benchmark.py

# regenerate the bundled dataset bit-for-bit
data: $(STAMP)
	$(VENV)/bin/slam2d simulate $(DATA) --seed 7

clean:
	rm -rf $(VENV) runs .pytest_cache

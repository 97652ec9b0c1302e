# Two entry points for a fresh machine; each creates/reuses .venv and installs what it needs.
PY ?= python3
VENV := .venv
STAMP := $(VENV)/.installed-stamp

.PHONY: demo demo-long test test-slow bench venv clean

$(STAMP): pyproject.toml
	test -x $(VENV)/bin/python || $(PY) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --upgrade pip
	$(VENV)/bin/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/equibim demo

demo-long: $(STAMP)
	$(VENV)/bin/equibim demo --train.batch-size 64 --train.total-steps 10000 --train.no-sym-stop-gradient --train.sym-batch-size None --out-dir results/demo10k

test: $(STAMP)
	$(VENV)/bin/python -m pytest -m "not slow" -q -n 2 --dist loadfile --durations=20

test-slow: $(STAMP)
	$(VENV)/bin/python tests/run_by_file.py -j 2 -m slow -o timeout=1800 -o timeout_method=thread

bench: $(STAMP)
	mkdir -p results && $(VENV)/bin/python benchmarks/sim.py --out results/bench_sim.json
	$(VENV)/bin/python benchmarks/report.py

clean:
	rm -rf $(VENV) *.egg-info

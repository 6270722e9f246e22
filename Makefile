# Two commands do all the set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test lint bench venv clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt torch==2.13.0
	$(PY) -m pip install --quiet -c constraints.txt -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/formation demo

# Two phases: the tests that only compute run two at a time (pytest-xdist); the ones that run
# nodes on the wall clock (marker realtime) run alone afterwards, on an otherwise idle machine.
# --dist loadgroup keeps the tests of one xdist_group (tests/xdist_groups.py) on one worker and
# hands the groups out first, as the largest units of work: the demo's tests share one quick demo
# run, and one local Ray runs at a time.
# The control tick's kernels are compiled into numba's cache first, once, rather than by both
# workers at the same time on a fresh clone.
test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -c "import stack.pipeline; from controllers.jit import warm_up; warm_up()"
	$(PY) -m pytest -q -n 2 --dist loadgroup -m "not realtime"
	$(PY) -m pytest -q -m realtime

lint: $(STAMP)
	$(VENV)/bin/ruff check .

bench: $(STAMP)
	$(PY) -m pip install --quiet -c constraints.txt -e '.[dev,bench]'
	$(PY) bench/sim_throughput.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info

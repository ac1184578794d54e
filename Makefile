# Two entry points: `make demo` (main job on the embedded synthetic default) and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-v1

.PHONY: install test test-slow demo clean

install: $(STAMP)

$(STAMP): setup.py constraints.txt Makefile
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e ".[dev,beam]"
	$(PY) -m pip install -q --no-deps waymo-open-dataset-tf-2-12-0==1.6.7
	touch $(STAMP)

test: install
	$(PY) -m pytest -q -m "not slow" tests

test-slow: install
	$(PY) -m pytest -q -m slow tests

demo: install
	$(PY) tools/demo.py --out_dir demo_out

clean:
	rm -rf demo_out .pytest_cache

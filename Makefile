# The two quick-start commands (`make demo`, `make test`) work on a fresh clone:
# each creates a local virtual environment, installs tpscore into it and runs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
SOURCES := pyproject.toml CMakeLists.txt $(shell find cpp python -type f -not -name '*.pyc' 2>/dev/null)

.PHONY: all install test demo bench bench-skin clean

all: install

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Reinstall whenever a source changes; the build folder makes it incremental.
$(VENV)/.installed: $(VENV)/bin/python $(SOURCES)
	$(PY) -m pip install --quiet ".[test,bench]"
	@touch $@

install: $(VENV)/.installed

test: install
	$(PY) -m pytest tests -q

demo: install
	$(VENV)/bin/tpscore demo --out demo-output

# Speed benchmarks (pytest-benchmark; ratios in bench-output/ratios.md), then the
# fidelity benchmark (bench-output/fidelity.md); both skip what needs ../shared if absent.
bench: install
	$(PY) -m pytest benchmarks -q -p no:cacheprovider -o python_files="bench_*.py" --benchmark-columns=min,median,mean,rounds --benchmark-sort=name
	$(PY) benchmarks/fidelity.py $(FIDELITY_ARGS)

# The physical skin's stability sweep and fidelity benchmark (about an hour on two
# cores; the fidelity part skips without ../shared): bench-output/skin_*.md.
bench-skin: install
	$(PY) benchmarks/skin_stability.py
	$(PY) benchmarks/skin_fidelity.py $(SKIN_FIDELITY_ARGS)

clean:
	rm -rf build $(VENV) demo-output .pytest_cache .benchmarks

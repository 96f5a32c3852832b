# The two quick-start commands (`make demo`, `make test`) work on a fresh clone:
# each creates a local virtual environment, installs tpscore into it and runs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
SOURCES := pyproject.toml CMakeLists.txt $(shell find cpp python -type f -not -name '*.pyc' 2>/dev/null)

.PHONY: all install test demo bench bench-skin sanitize clean

all: install

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Reinstall whenever a source changes; the build folder makes it incremental. The usd
# extra is installed too, so that the tests exercise the rigs' USD output.
# The first install says so and shows pip's steps: it compiles the C++ core, which takes
# one to three minutes. A rebuild after an edit takes seconds and stays quiet, so that
# `make test` prints the tests.
FIRST_INSTALL = $(if $(wildcard $(VENV)/.installed),,yes)
$(VENV)/.installed: $(VENV)/bin/python $(SOURCES)
	@$(if $(FIRST_INSTALL),echo "tpscore: the first build compiles the C++ core into $(VENV); it takes 1-3 minutes",true)
	$(PY) -m pip install $(if $(FIRST_INSTALL),--progress-bar on,--quiet) ".[test,bench,usd]"
	@$(if $(FIRST_INSTALL),echo "tpscore: installed",true)
	@touch $@

install: $(VENV)/.installed

# The kernels pick their instruction set at import (AVX-512, AVX2 or the x86-64
# baseline, lowered by TPSCORE_SIMD): after the whole suite, the kernel tests run again
# under each lower set this CPU has, the AVX2 run with NumPy's own AVX-512 paths off as
# on a CPU without them, so a developer on any CPU exercises every kernel path.
KERNEL_TESTS ?= tests/test_rbf.py tests/test_csrbf.py tests/test_spatial.py tests/test_mesh.py \
	tests/test_sparse.py tests/test_raster.py tests/test_skin_sim.py tests/test_registration.py tests/test_pickling.py
NUMPY_WITHOUT_AVX512 := AVX512F AVX512CD AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR
LOWER_SIMD = $(PY) -c "from tpscore import _core; order = ['avx512', 'avx2', 'baseline']; \
	print(' '.join(order[order.index(_core.simd_level()) + 1:]))"

test: install
	$(PY) -m pytest tests -q
	@for level in $$($(LOWER_SIMD)); do \
		echo "kernel tests with TPSCORE_SIMD=$$level"; \
		TPSCORE_SIMD=$$level NPY_DISABLE_CPU_FEATURES="$(NUMPY_WITHOUT_AVX512)" \
			$(PY) -m pytest $(KERNEL_TESTS) -q -p no:cacheprovider || exit 1; \
	done

demo: install
	$(VENV)/bin/tpscore demo --out demo-output

# Speed benchmarks (pytest-benchmark; ratios in bench-output/ratios.md), then the
# fidelity benchmark (bench-output/fidelity.md), a transfer's cost against grid and scan
# size (bench-output/transfer_scale.md) and the batch engine's throughput
# (bench-output/batch_throughput.md); all skip what needs ../shared if absent.
BENCH_PYTEST = $(PY) -m pytest -q -p no:cacheprovider -o python_files="bench_*.py" \
	--benchmark-columns=min,median,mean,rounds --benchmark-sort=name
# The kernels' benchmarks again at each lower instruction set the CPU has (NumPy's own
# AVX-512 paths off as well, as on a CPU without them, and OpenBLAS held to that set's
# kernels, so that the arithmetic limits come from that set's peak):
# bench-output/ratios-<set>.md.
KERNEL_BENCHMARKS ?= benchmarks/bench_rbf.py benchmarks/bench_csrbf.py benchmarks/bench_spatial.py \
	benchmarks/bench_sparse.py benchmarks/bench_lattice.py benchmarks/bench_mesh.py

bench: install
	$(BENCH_PYTEST) benchmarks
	@for level in $$($(LOWER_SIMD)); do \
		echo "kernel benchmarks with TPSCORE_SIMD=$$level"; \
		TPSCORE_SIMD=$$level NPY_DISABLE_CPU_FEATURES="$(NUMPY_WITHOUT_AVX512)" \
			OPENBLAS_CORETYPE=$$(if [ $$level = avx2 ]; then echo Haswell; else echo Prescott; fi) \
			$(BENCH_PYTEST) $(KERNEL_BENCHMARKS) || exit 1; \
	done
	$(PY) benchmarks/fidelity.py $(FIDELITY_ARGS)
	$(PY) benchmarks/transfer_scale.py
	$(PY) benchmarks/batch_throughput.py

# The physical skin's stability sweep, fidelity benchmark and smile strength (about an
# hour and a half on a shared two-core machine; the last two skip without ../shared):
# bench-output/skin_*.md, recorded in benchmarks/SKIN.md.
bench-skin: install
	$(PY) benchmarks/skin_stability.py
	$(PY) benchmarks/skin_fidelity.py $(SKIN_FIDELITY_ARGS)
	$(PY) benchmarks/skin_smile.py
	$(PY) benchmarks/skin_heldout.py

# The kernels built with AddressSanitizer + UndefinedBehaviorSanitizer into an environment
# of their own, and the kernel tests run under them (the kernels' own tests, the rows of
# the bad-input battery that do not run whole transfers, the lattice kernel's tests): a
# finding aborts the run with its stack trace. Python itself is not instrumented, so the
# sanitizer runtimes are preloaded; leaks are not checked (the interpreter keeps its own
# memory to the end). The build requirements (the versions pyproject.toml pins, CMake
# and Ninja) go into the environment itself rather than into a new isolated one each
# time, so that a rebuild after an edit is incremental.
SANITIZE_VENV ?= .venv-sanitize
SANITIZE_TESTS ?= tests/test_rbf.py tests/test_csrbf.py tests/test_spatial.py tests/test_mesh.py \
	tests/test_sparse.py tests/test_raster.py tests/test_skin_sim.py tests/test_bad_input.py tests/test_registration.py
SANITIZE_RUN = LD_PRELOAD="$$($(CXX) -print-file-name=libasan.so) $$($(CXX) -print-file-name=libubsan.so)" \
	ASAN_OPTIONS=detect_leaks=0:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
	$(SANITIZE_VENV)/bin/python -m pytest -q -p no:cacheprovider
sanitize:
	$(PYTHON) -m venv $(SANITIZE_VENV)
	$(SANITIZE_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(SANITIZE_VENV)/bin/python -m pip install --quiet scikit-build-core "nanobind==2.9.2" "cmeel-eigen==3.4.1" \
		"cmake>=3.18" ninja
	$(SANITIZE_VENV)/bin/python -m pip install --quiet --no-build-isolation ".[test]" \
		-C cmake.define.TPSCORE_SANITIZE=ON -C cmake.build-type=RelWithDebInfo -C build-dir=build/sanitize
	$(SANITIZE_RUN) $(SANITIZE_TESTS) -k "not pipeline"

clean:
	rm -rf build $(VENV) $(SANITIZE_VENV) demo-output .pytest_cache .benchmarks

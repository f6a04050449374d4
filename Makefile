# The two entry points of the project: `make demo` and `make test`.
# Each creates the project virtual environment (.venv) when missing and installs what it needs,
# Debian packages included where a dependency needs them.
# `make test` also runs the suite on Python 3.10 (the drone's Python) in a second environment,
# .venv310, whenever a 3.10 interpreter is found (PYTHON310=/path/to/python3.10 to choose one).

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# The first working Python 3.10: python3.10 on PATH (a pyenv shim only works when pyenv has 3.10
# selected, so it is run to be sure), else the newest 3.10 that pyenv has built.
ifeq ($(origin PYTHON310), undefined)
PYTHON310 := $(shell for c in python3.10 \
	$$(ls -d "$$(pyenv root 2>/dev/null || echo $$HOME/.pyenv)"/versions/3.10.* 2>/dev/null \
	  | sort -V -r | sed 's|$$|/bin/python3.10|'); do \
	"$$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 10))' >/dev/null 2>&1 \
	  && { command -v "$$c"; break; }; done)
endif
VENV310 := .venv310
PY310 := $(VENV310)/bin/python
STAMP310 := $(VENV310)/.installed
export OPENBLAS_NUM_THREADS := 1
export OMP_NUM_THREADS := 1
export MPLBACKEND := Agg

.PHONY: demo test lint typecheck pytest pytest310 prepare310 check-default bench check-target \
	system-deps clean

# Debian packages: venv support for the interpreter, the shared libraries Open3D loads,
# systemd-analyze (the tests verify the units) and openssl (swarm-gcs certs makes the demo CA).
system-deps:
	@need=""; \
	$(PYTHON) -c "import venv, ensurepip" 2>/dev/null || need="$$need python3-venv"; \
	ldconfig -p 2>/dev/null | grep -q libgomp.so.1 || need="$$need libgomp1"; \
	ldconfig -p 2>/dev/null | grep -q libGL.so.1 || need="$$need libgl1"; \
	command -v systemd-analyze >/dev/null 2>&1 || need="$$need systemd"; \
	command -v openssl >/dev/null 2>&1 || need="$$need openssl"; \
	if [ -n "$$need" ]; then \
		echo "installing Debian packages:$$need"; \
		if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
		$$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$need; \
	fi

$(STAMP): pyproject.toml | system-deps
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev]"
	touch $(STAMP)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

typecheck: $(STAMP)
	$(VENV)/bin/mypy onboard gcs sitl_mock

# Tests. Every test runs on every core (pytest-xdist, a worker per core and one more) except
# the timing-sensitive flights against the mock, which run afterwards: those marked `fleet` (its
# fleet, flight services, the demo) one at a time, and beside them those marked `vehicle` (one
# vehicle flown and landed: light) one at a time. The whole suite runs once, on Python 3.10: the
# drone's interpreter, and everything runs there (the ground station and the mock too). On the
# default interpreter (the `.venv` that `make demo` uses) a smoke selection checks that
# environment: every module imports, numba compiles and runs kernels there (the
# small ones: the planner's and the mapping's big kernels are the same code under the same
# numba, compiled and tested on 3.10; compiling them cold again costs ~135 s of CPU), the
# mock, the bus, the view and the report. Without a 3.10 interpreter the whole suite runs on
# the default one. The smoke runs in one process: phase one is bound by CPU, and each xdist
# worker would compile the mock's kernels again (measured: 85 s on two workers beside the 3.10
# kernels, phase one ending at ~280 s).
#
# `make test` goes in two phases. First, side by side (two jobs; mostly installing and
# compiling, which do not mind sharing the cores): the default environment (install, lint,
# types, smoke) and the 3.10 one (install, kernels). Then the 3.10 suite alone.
# One xdist worker more than the cores: some of these tests wait on real time (a vehicle of the
# mock flown, a link timed out), and meanwhile a spare worker keeps the cores busy. 2 cores
# (AMD EPYC, 2026-11-28): 2 workers 209-213 s, 3 workers 177-178 s, 4 workers 180-199 s.
# (nproc counts OMP_NUM_THREADS, which this Makefile exports as 1 to every sub-make: without the
# `env -u`, `make test`'s own recursive call ran 2 workers, not 3, on this machine)
PYTEST_PARALLEL := -m "not fleet and not vehicle" -n $(shell echo $$(( $$(env -u OMP_NUM_THREADS nproc) + 1 )))
# The flights' runs collect only the files that mark such tests (collecting all ~1200 tests
# costs ~10 s a run); -m still selects the tests within them.
# The flights: the fleet's (FLIGHTS_fleet) one at a time, and beside them, in a second pytest,
# the single vehicles' (FLIGHTS_vehicle) one at a time (`make -j2 --output-sync`: each run's
# output printed whole). A vehicle flight is light (~0.35 of a core); the fleet's average about
# one core, the demo's 1.6, so the demo goes last, after the ~2 minutes of vehicle flights.
# (Before: the vehicle run, 2 at a time, 49 s, then the fleet run alone, ~280 s; BENCHMARKS
# section 11.) pytest-xdist's `--dist loadgroup` would do this in one run, but its group marks
# do nothing under pytest 9 (it renames `item._nodeid`, which pytest 9 no longer reads).
FLEET_FILES := $(shell grep -l "mark\.fleet" tests/test_*.py)
FLIGHTS_fleet := -m fleet $(filter-out tests/test_demo.py,$(FLEET_FILES)) \
	$(filter tests/test_demo.py,$(FLEET_FILES))
FLIGHTS_vehicle := -m vehicle $(shell grep -l "mark\.vehicle" tests/test_*.py)
KERNEL_SMOKE := $(addprefix tests/test_planner_kernels.py::test_,np_sum_is_numpys_pairwise_sum \
	norm3_is_numpys_norm np_linspace_is_numpys np_arange_is_numpys np_interp_is_numpys \
	position_kernels_are_eval_piecewise)
SMOKE_TESTS := tests/test_imports.py tests/test_layers.py $(KERNEL_SMOKE) \
	tests/test_sitl_autopilot.py tests/test_zenoh_bus.py tests/test_view.py tests/test_report.py
# numba's kernels compiled once, two processes side by side, before the xdist workers start
# (else each worker compiles the same kernels at the same time: tests/warm_kernels.py). First
# the packages' bytecode, written once: where PYTHONDONTWRITEBYTECODE is set (this machine's
# environment sets it) every one of the suite's processes would compile them again on import.
WARM = $(1) -m compileall -q onboard gcs sitl_mock || exit 1; \
	$(1) tests/warm_kernels.py planner & p=$$!; $(1) tests/warm_kernels.py rest; r=$$?; \
	wait $$p && test $$r = 0
pytest: $(STAMP)
ifeq ($(strip $(PYTHON310)),)
	@$(call WARM,$(PY))
	$(VENV)/bin/pytest -q $(PYTEST_PARALLEL)
	@$(MAKE) --no-print-directory -j2 --output-sync=target flights-fleet flights-vehicle
else
	$(VENV)/bin/pytest -q -m "not slow" $(SMOKE_TESTS)
endif

# The same environment and suite on Python 3.10. numba names its cache files after the Python
# version (*.py310.nbi next to *.py311.nbi), so the two runs do not overwrite each other's kernels.
$(STAMP310): pyproject.toml | system-deps
	@test -n "$(PYTHON310)" || { echo "no Python 3.10 interpreter (set PYTHON310=...)"; exit 1; }
	@$(PYTHON310) -c "import venv, ensurepip" 2>/dev/null || { \
		echo "installing Debian package python3.10-venv"; \
		if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq python3.10-venv; }
	test -x $(PY310) || $(PYTHON310) -m venv $(VENV310)
	$(PY310) -m pip install -q --upgrade pip
	$(PY310) -m pip install -q -e ".[dev]"
	touch $(STAMP310)

ifeq ($(strip $(PYTHON310)),)
prepare310:
	@true
pytest310:
	@echo "pytest310: no Python 3.10 interpreter found (see README): the suite runs on $$($(PYTHON) -V 2>&1) only"
else
prepare310: $(STAMP310)
	@$(call WARM,$(PY310))
pytest310: prepare310
	$(VENV310)/bin/pytest -q -p no:cacheprovider $(PYTEST_PARALLEL)
	@$(MAKE) --no-print-directory -j2 --output-sync=target flights310-fleet flights310-vehicle
endif

flights-%: $(STAMP)
	$(VENV)/bin/pytest -q $(FLIGHTS_$*)
flights310-%: $(STAMP310)
	$(VENV310)/bin/pytest -q -p no:cacheprovider $(FLIGHTS_$*)

# Phase one's two jobs (each one's output printed in one piece), then the 3.10 suite alone
# (its kernels are cached by then: its WARM only loads them, a few seconds).
check-default: lint typecheck
	@$(MAKE) --no-print-directory pytest
test:
	@$(MAKE) --no-print-directory -j2 --output-sync=target check-default prepare310
	@$(MAKE) --no-print-directory pytest310

# The 7-drone hexagon through forest-medium, re-shaped into a rectangle 20 s after the goal, with
# the demo's defaults for 7 drones (3 depth frames/s, the altitude band 0.4-1.8 m): what this
# 2-core machine sustains in real time (BENCHMARKS.md section 10, 2026-11-27: 5 of 5 seeds with
# and without the change on the slowest host seen).
demo: $(STAMP)
	$(VENV)/bin/swarm-gcs demo --drones 7 --formation hexagon-7 --world forest-medium --seed 1 \
		--formation-change rectangle-7@20

bench: $(STAMP)
	$(VENV)/bin/swarm-gcs bench planner --json out/bench_planner.json

# The drone target (Jetson Xavier NX: aarch64, glibc 2.31, Python 3.10) must install every
# dependency from wheels: resolve the pinned set for that platform without installing it.
# The requirements are read from the installed project's metadata (the stamp keeps it in step
# with pyproject.toml), which works on Python 3.10 too (no tomllib).
check-target: $(STAMP)
	rm -rf build/target-wheels
	$(PY) -m pip download -q --dest build/target-wheels --only-binary=:all: \
		--platform manylinux_2_31_aarch64 --platform manylinux_2_28_aarch64 \
		--platform manylinux_2_27_aarch64 --platform manylinux_2_24_aarch64 \
		--platform manylinux_2_17_aarch64 --platform manylinux2014_aarch64 \
		--python-version 3.10 --implementation cp \
		$$($(PY) -c "from importlib.metadata import requires; \
			reqs = [r.replace(' ', '') for r in requires('swarm-formation')]; \
			print(*(r for r in reqs if ';extra==' not in r))")
	ls build/target-wheels

clean:
	rm -rf $(VENV) $(VENV310) build *.egg-info .mypy_cache .ruff_cache .pytest_cache

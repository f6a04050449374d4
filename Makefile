# The two entry points of the project: `make demo` and `make test`.
# Each creates the project virtual environment (.venv) when missing and installs what it needs,
# Debian packages included where a dependency needs them.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export OPENBLAS_NUM_THREADS := 1
export OMP_NUM_THREADS := 1
export MPLBACKEND := Agg

.PHONY: demo test lint typecheck pytest bench check-target system-deps clean

# Debian packages: venv support for the interpreter and the shared libraries Open3D loads.
system-deps:
	@need=""; \
	$(PYTHON) -c "import venv, ensurepip" 2>/dev/null || need="$$need python3-venv"; \
	ldconfig -p 2>/dev/null | grep -q libgomp.so.1 || need="$$need libgomp1"; \
	ldconfig -p 2>/dev/null | grep -q libGL.so.1 || need="$$need libgl1"; \
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
	$(VENV)/bin/mypy onboard/planner onboard/mapping onboard/sensors

pytest: $(STAMP)
	$(VENV)/bin/pytest -q

test: lint typecheck pytest

demo: $(STAMP)
	$(VENV)/bin/swarm-gcs sim --formation hexagon-7 --world forest-medium --seed 1

bench: $(STAMP)
	$(VENV)/bin/swarm-gcs bench planner --json out/bench_planner.json

# The drone target (Jetson Xavier NX: aarch64, glibc 2.31, Python 3.10) must install every
# dependency from wheels: resolve the pinned set for that platform without installing it.
check-target: $(STAMP)
	rm -rf build/target-wheels
	$(PY) -m pip download -q --dest build/target-wheels --only-binary=:all: \
		--platform manylinux_2_31_aarch64 --platform manylinux_2_28_aarch64 \
		--platform manylinux_2_27_aarch64 --platform manylinux_2_24_aarch64 \
		--platform manylinux_2_17_aarch64 --platform manylinux2014_aarch64 \
		--python-version 3.10 --implementation cp \
		$$($(PY) -c "import tomllib; print(' '.join(repr(d) for d in tomllib.load(open('pyproject.toml','rb'))['project']['dependencies']))" | tr -d "'")
	ls build/target-wheels

clean:
	rm -rf $(VENV) build *.egg-info .mypy_cache .ruff_cache .pytest_cache

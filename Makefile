# hammer_ros developer entry points. Everything installs into .venv/ at the repo root,
# with the exact versions of requirements/lock.txt; `make setup` is idempotent.
VENV      := .venv
PYTHON    ?= python3
BIN       := $(VENV)/bin
STAMP     := $(VENV)/.installed-stamp
PYTEST_ARGS ?=
# pytest-xdist processes of make test (make test TEST_WORKERS=0: the suite in one process)
TEST_WORKERS ?= 2
export OPENBLAS_NUM_THREADS ?= 1

.PHONY: setup test demo lint reproduce bench bench-deps clean

setup: $(STAMP)

$(STAMP): setup.py requirements/lock.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	env -u LD_LIBRARY_PATH -u _ROS_WHEELS_BOOTSTRAP_COMPLETE $(BIN)/python -m pip install -q --disable-pip-version-check \
	    -c requirements/lock.txt -e ".[ros,fleet,test]"
	touch $(STAMP)

test: setup
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadscope $(PYTEST_ARGS)

demo: setup
	$(BIN)/hammer-ros demo

lint: setup
	$(BIN)/ruff check hammer_ros test

reproduce: setup
	$(BIN)/hammer-ros reproduce all

# the peers of the benchmark (SysIdentPy), installed into .venv only for `hammer-ros bench`
bench-deps: setup
	env -u LD_LIBRARY_PATH -u _ROS_WHEELS_BOOTSTRAP_COMPLETE $(BIN)/python -m pip install -q --disable-pip-version-check \
	    --no-deps -r requirements/bench.txt

bench: bench-deps
	$(BIN)/hammer-ros bench

clean:
	rm -rf $(VENV) build install log *.egg-info

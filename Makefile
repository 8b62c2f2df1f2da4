# febed — every target sets itself up on a fresh Debian 12 machine.
SHELL := /bin/bash
VENV  := .venv
PY    := $(VENV)/bin/python
STAMP := $(VENV)/.febed-setup
DEB_PKGS := python3-dolfinx python3-petsc4py python3-mpi4py python3-numba python3-gmsh python3-pytest \
            python3-pytest-xdist python3-pytest-timeout \
            python3-matplotlib python3-h5py python3-scipy python3-venv python3-pip python3-setuptools \
            openmpi-bin
# root needs sudo-less apt and mpirun --allow-run-as-root; a normal user needs sudo for apt only.
IS_ROOT := $(shell [ "$$(id -u)" = 0 ] && echo yes)
SUDO    := $(if $(IS_ROOT),,sudo)
MPIEXEC := mpirun $(if $(IS_ROOT),--allow-run-as-root) --oversubscribe
MPIRUN  := $(MPIEXEC) -n 2
PYTEST  := $(PY) -m pytest
# processes of the serial tests (pytest-xdist; one test file per process at a time): `make test TEST_WORKERS=4`
TEST_WORKERS ?= 2
# $(call apt_ensure,PACKAGES): apt-get install those of the Debian PACKAGES that are not installed yet.
apt_ensure = missing=""; for p in $(1); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "febed: installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q $$missing; \
	fi
export OMPI_MCA_rmaps_base_oversubscribe := 1

.PHONY: setup demo test test-serial test-mpi test-ranks test-all bench lint docs clean
setup: $(STAMP)

$(STAMP): pyproject.toml
	@$(call apt_ensure,$(DEB_PKGS))
	[ -x $(PY) ] || /usr/bin/python3 -m venv --system-site-packages $(VENV)
	$(PY) -m pip install -q --no-build-isolation -e '.[dev]'
	@touch $(STAMP)

# The default demo: the seed-000 2D bubbling bed, 0.3 s of it (demos/wang2d/, a few minutes).
demo: setup
	$(PY) demos/wang2d/demo_wang2d.py --end-time 0.3

test: setup lint test-serial test-mpi

test-serial: setup
	$(PYTEST) -m "not slow" -n $(TEST_WORKERS) --dist loadfile

# The MPI tests on 2 ranks, and the many-rank tests (partition corners, restarts onto fewer ranks) on 4.
test-mpi: setup
	$(MPIRUN) $(PY) -m pytest -m "mpi and not slow" -q --color=no
	$(MPIEXEC) -n 4 $(PY) -m pytest -m "mpi and not slow" -q --color=no tests/parallel/test_many_ranks.py

# The distributed particle tests on 3, 4 and 8 ranks (oversubscribed), PCPM events across the partitions among
# them, and the 4 -> 2 -> 1 restart through `febed run`.
test-ranks: setup
	for n in 3 4; do $(MPIEXEC) -n $$n $(PY) -m pytest -m mpi -q --color=no tests/parallel tests/coarse/test_pcpm_mpi.py \
		|| exit 1; done
	$(MPIEXEC) -n 8 $(PY) -m pytest -m mpi -q --color=no tests/parallel/test_mpi_dem.py tests/parallel/test_many_ranks.py \
		tests/parallel/test_mpi_owner_coupling.py tests/coarse/test_pcpm_mpi.py
	$(PYTEST) -m slow tests/parallel/test_many_ranks.py

test-all: setup test-ranks
	$(PYTEST)
	$(MPIRUN) $(PY) -m pytest -m mpi -q --color=no

bench: setup
	@for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

lint: setup
	$(VENV)/bin/ruff check febed tests benchmarks demos
	$(VENV)/bin/ruff format --check --quiet febed tests benchmarks demos
	$(PY) tools/check_language.py
	$(PY) tools/check_layers.py

# The documentation site (docs/, Sphinx + MyST Markdown from Debian's packages) in docs/_build/html; warnings are
# errors. The case-file reference and the API pages are generated from febed's code at every build.
DOC_PKGS := python3-sphinx python3-myst-parser
docs: setup
	@$(call apt_ensure,$(DOC_PKGS))
	$(PY) -m sphinx -b html -W --keep-going -q -E docs docs/_build/html
	@echo "febed docs: open docs/_build/html/index.html"

clean:
	rm -rf $(VENV) docs/_build

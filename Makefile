# slicersim developer entry points.  `make demo` and `make test` bootstrap
# everything: the virtual environment, the package and an OpenCL runtime.

VENV    ?= .venv
PYTHON3 ?= python3
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.slicersim-installed
UV      := $(shell command -v uv 2>/dev/null)

OPENCL_CHECK := "$(PY)" -c "import pyopencl; assert pyopencl.get_platforms()"
OPENCL_PKGS  := pocl-opencl-icd ocl-icd-libopencl1
OPENCL_VENDORS ?= /etc/OpenCL/vendors

.PHONY: venv opencl test demo bench clean distclean

venv: $(STAMP)

# Re-run the install only when the package metadata changes.
$(STAMP): pyproject.toml
	@if [ ! -x "$(PY)" ]; then \
	  if [ -n "$(UV)" ]; then echo "creating $(VENV) with uv"; uv venv "$(VENV)"; \
	  else echo "creating $(VENV) with $(PYTHON3) -m venv"; $(PYTHON3) -m venv "$(VENV)"; fi; \
	fi
	@if [ -n "$(UV)" ]; then uv pip install --python "$(PY)" -e ".[test,galaxies]"; \
	else "$(PY)" -m pip install -e ".[test,galaxies]"; fi
	@touch "$@"

# Make sure pyopencl sees at least one OpenCL platform; install PoCL otherwise.
opencl: venv
	@if $(OPENCL_CHECK) >/dev/null 2>&1; then exit 0; fi; \
	if ls $(OPENCL_VENDORS)/*.icd >/dev/null 2>&1; then \
	  echo "error: an OpenCL ICD is registered in $(OPENCL_VENDORS) but pyopencl finds no platform." >&2; \
	  echo "       Check the driver with 'clinfo' and '$(VENV)/bin/slicersim info'." >&2; \
	  exit 1; \
	fi; \
	if [ "$$(id -u)" = 0 ]; then SUDO=""; \
	elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then SUDO="sudo -n"; \
	else \
	  echo "error: no OpenCL runtime found and cannot install one (not root, no passwordless sudo)." >&2; \
	  echo "       Install the PoCL CPU runtime, e.g. on Debian/Ubuntu:" >&2; \
	  echo "         sudo apt-get install $(OPENCL_PKGS)" >&2; \
	  echo "       or any vendor OpenCL driver (NVIDIA, AMD ROCm, Intel), then re-run make." >&2; \
	  exit 1; \
	fi; \
	if ! command -v apt-get >/dev/null 2>&1; then \
	  echo "error: no OpenCL runtime found and apt-get is unavailable; install PoCL ($(OPENCL_PKGS)) or a vendor OpenCL driver." >&2; \
	  exit 1; \
	fi; \
	echo "no OpenCL platform found: installing $(OPENCL_PKGS) with apt-get"; \
	$$SUDO apt-get update && \
	DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y --no-install-recommends $(OPENCL_PKGS) && \
	if ! $(OPENCL_CHECK); then \
	  echo "error: PoCL was installed but pyopencl still finds no OpenCL platform." >&2; exit 1; \
	fi

# -rs lists every skipped test and why (e.g. no ../shared/reference, no fp64 OpenCL device);
# with CI=true a missing ../shared/reference fails the reference tests instead of skipping them.
test: venv opencl
	"$(PY)" -m pytest -q -rs

demo: venv opencl
	"$(VENV)/bin/slicersim" demo --outdir demo_output

bench: venv opencl
	@set -e; found=0; for f in benchmarks/*.py; do \
	  case "$$(basename "$$f")" in _*) continue;; esac; \
	  [ -e "$$f" ] || continue; found=1; echo "== $$f"; "$(PY)" "$$f"; \
	done; [ $$found = 1 ] || echo "no benchmark scripts in benchmarks/"

clean:
	rm -rf build dist *.egg-info .pytest_cache .hypothesis demo_output
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf "$(VENV)"

# Two commands do all set-up on a fresh machine: `make demo` and `make test`.
# Every target is idempotent; `setup` re-runs pip only when pyproject.toml changes.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed
TORCH  := torch==2.13.0
# PyPI's Linux torch is the CUDA build (gigabytes); PyTorch's CPU index serves 2.13.0+cpu,
# which pip prefers to it (a local version sorts after the public one). Where that index
# cannot be reached pip says so (one retry, 15 s at most a try) and takes what its own
# configuration offers: a local CPU wheel where one is set up, else PyPI's build.
TORCH_CPU_INDEX := https://download.pytorch.org/whl/cpu
# Dr.Jit's LLVM backend aborts on libLLVM 15; any libLLVM >= 17 works.
LLVM_GLOB := /usr/lib/*/libLLVM.so.1[7-9]* /usr/lib/*/libLLVM.so.[2-9][0-9]* /usr/lib/*/libLLVM-1[7-9]*.so* /usr/lib/*/libLLVM-[2-9][0-9]*.so* /usr/lib/llvm-1[7-9]/lib/libLLVM*.so* /usr/lib/llvm-[2-9][0-9]/lib/libLLVM*.so*

.PHONY: setup llvm test test-fast lint bench clean demo demo-train

setup: llvm $(STAMP)

llvm:
	@# One existing match is enough (ls over all the patterns fails when any one is absent).
	@found=; for f in $(LLVM_GLOB); do [ -e "$$f" ] && found=1; done; \
	if [ -n "$$found" ]; then :; else \
	  echo "libLLVM >= 17 not found: installing Debian's libllvm19"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	  $$SUDO apt-get update -qq && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19; \
	fi

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	# CPU torch first, pinned, so that nothing pulls CUDA wheels.
	$(PIP) install -q $(TORCH) --extra-index-url $(TORCH_CPU_INDEX) --retries 1 --timeout 15
	$(PIP) install -q -e '.[dev]'
	touch $(STAMP)

# Test processes: one per core, at most 4 (each holds its own Mitsuba kernels and fixtures).
# A file's tests stay in one process (--dist loadfile), so its module fixtures are built once.
TEST_JOBS ?= $(shell n=$$(nproc 2>/dev/null || echo 1); [ "$$n" -gt 4 ] && n=4; echo $$n)
PYTEST    := $(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile

test: setup
	$(PYTEST)

# The inner loop while developing: everything but the tests marked slow (end-to-end runs).
test-fast: setup
	$(PYTEST) -m "not slow"

lint: setup
	$(VENV)/bin/ruff check sq_mitsuba tests

bench: setup
	$(VENV)/bin/sq-mitsuba bench all

# Unseen spacecraft in, assemblies and poses out: demo_output/index.html (a minute and a half).
demo: setup
	$(VENV)/bin/sq-mitsuba demo

# The same after training a small model from scratch (measured 2.6-5.8 min on 2 cores).
demo-train: setup
	$(VENV)/bin/sq-mitsuba demo --train

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache *.egg-info

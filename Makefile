# Two commands do all the set-up on a fresh machine:  make train   /   make test
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
ARGS   ?=
PYTEST_ARGS ?=
# A CPU torch wheel among pip's find-links (this machine: /opt/wheels) is used as it is; else PyTorch's CPU index.
TORCH_INDEX ?= $(shell for d in $${PIP_FIND_LINKS:-} $$($(PYTHON) -m pip config get global.find-links 2>/dev/null); do \
  ls "$$d"/torch-2.13.0+cpu-*.whl >/dev/null 2>&1 && exit 0; done; \
  echo --extra-index-url https://download.pytorch.org/whl/cpu)

.PHONY: venv sysdeps train test test-fast reconstruct evaluate phantom clean

# open3d needs libusb-1.0 (Debian: libusb-1.0-0); installed when missing and we may use apt.
sysdeps:
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then \
	  if command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ]; then \
	    echo "installing Debian packages libusb-1.0-0 libgomp1 (needed by open3d)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null; \
	  else \
	    echo "open3d needs libusb-1.0: run 'sudo apt-get install libusb-1.0-0' (Debian/Ubuntu)"; exit 1; \
	  fi; \
	fi

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# The pinned CPU wheel first: an unpinned torch would pull a multi-GB CUDA build (and PyPI's torch==2.13.0
	# is the CUDA build too: without a local CPU wheel, PyTorch's CPU index is asked).
	$(BIN)/pip install -q torch==2.13.0 $(TORCH_INDEX)

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e ".[dev]"
	touch $@

venv: sysdeps $(VENV)/.installed

# The default job: bootstrapped training on the generated phantom (CPU schedule), held-out patient's mesh.
train: venv
	$(BIN)/python train.py $(ARGS)

test: venv
	$(BIN)/python -m pytest $(PYTEST_ARGS)

test-fast: venv
	$(BIN)/python -m pytest -m "not slow" $(PYTEST_ARGS)

reconstruct: venv
	$(BIN)/python reconstruct.py $(ARGS)

evaluate: venv
	$(BIN)/python evaluate.py $(ARGS)

phantom: venv
	$(BIN)/python -m endorecon.phantom $(ARGS)

clean:
	rm -rf outputs .pytest_cache

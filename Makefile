# One command sets up and runs the flagship scene (make demo); one runs the tests (make test).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# System libraries: libusb for open3d, Mesa's Vulkan driver for the GPU-backend check,
# OSMesa/EGL for pyvista's offscreen rendering, SuiteSparse's headers for scikit-sparse (CHOLMOD).
SYSTEM_PACKAGES := libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libgl1 libegl1 libosmesa6 libxrender1 libsuitesparse-dev

.PHONY: setup system demo test test-all bench figures clean

setup: system $(STAMP)

system:
	@missing=""; for p in $(SYSTEM_PACKAGES); do \
	  dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
	  $$SUDO apt-get update -qq && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	fi

$(STAMP): setup.cfg pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[all]'
	touch $(STAMP)

demo: setup
	$(VENV)/bin/tissue run liver --out figures/liver

# One pytest worker per core (pytest-xdist), a test file per worker: compiling kernels, most of
# a cold run, is single-threaded.
test: setup
	$(PY) -m pytest -q -n auto --dist loadfile

test-all: setup
	$(PY) -m pytest -q -n auto --dist loadfile -m ""

bench: setup
	$(PY) -m bench.deformation
	$(PY) -m bench.contact
	$(PY) -m bench.haptics
	$(PY) -m bench.accuracy
	$(PY) -m bench.stability

figures: demo
	$(VENV)/bin/tissue run beam --out figures/beam
	$(VENV)/bin/tissue run organs --out figures/organs
	$(VENV)/bin/tissue run incline --out figures/incline
	$(VENV)/bin/tissue run liver_press --out figures/liver_press
	$(VENV)/bin/tissue run liver_grasp --out figures/liver_grasp
	$(VENV)/bin/tissue run liver_cut --out figures/liver_cut

clean:
	rm -rf $(VENV) out build *.egg-info

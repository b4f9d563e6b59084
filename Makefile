# Two entry points for a newcomer: `make demo` and `make test`.
# Both create .venv with the project installed; nothing needs installing by hand.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: venv test demo demo-ros2 demo-async bench lint schemas clean browser native compiler node-deps

$(STAMP): pyproject.toml clients/python/pyproject.toml setup.py mypyc.ini | compiler
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]' -e 'clients/python[plots,viz]'
	touch $(STAMP)

venv: $(STAMP) native

# The daemon's hot modules (pd_service/native.py) are compiled with mypyc at install when a C
# compiler and Python's headers are there; installed here when missing and possible (root
# and apt-get), else the package runs as pure Python (same results, slower).
compiler:
	@if command -v cc >/dev/null && $(PYTHON) -c "import os, sys, sysconfig; \
	  sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()['include'], 'Python.h')))"; then :; \
	elif [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then \
	  echo "make: no C compiler or Python headers, and no root apt-get: the hot path runs as pure Python"; \
	else \
	  echo "make: installing gcc and python3-dev (apt-get) to compile the hot path"; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq gcc python3-dev >/dev/null) \
	    || echo "make: apt-get could not install them: the hot path runs as pure Python"; \
	fi

# A compiled build older than its sources is never run (pd_service.native runs the .py files
# instead, with a warning); here it is rebuilt.
native: $(STAMP)
	@$(PY) -W ignore -c "import sys, pd_service.native as n; sys.exit('stale' in n.STATUS)" \
	  || { echo "make: rebuilding the compiled hot path (its sources changed)"; \
	       $(PY) -m pip install --quiet --no-deps -e .; }
	@$(PY) -c "import pd_service.native as n; print('make: hot path:', n.STATUS)"

# The demo's PNG plots need matplotlib (the client's `plots` extra), its live view and MCAP
# log foxglove-sdk and mcap (`viz`), both installed above.
demo: $(STAMP) native
	$(VENV)/bin/pd-demo

# The ROS 2 variant (rosbags, in the dev extra): docs/ros2.md.
demo-ros2: $(STAMP)
	$(VENV)/bin/pd-demo --ros2

# Sensors off the step grid, stamped with their own time (issue 42): docs/clients.md.
demo-async: $(STAMP) native
	$(VENV)/bin/pd-demo --async

# The whole suite on the installed build (compiled where it could be), then the hot modules'
# own tests again on their .py files (PD_SERVICE_PURE=1: the pure-Python reference; the C
# kernels' own tests need the kernels, so they run in the first pass).
PURE_TESTS := tests/estimation tests/intake tests/wire/test_convert.py tests/service/test_core.py \
	tests/service/test_health.py tests/service/test_robot_time.py tests/test_native.py

test: $(STAMP) native browser node-deps
	$(PY) -m pytest -q
	PD_SERVICE_PURE=1 $(PY) -m pytest -q $(PURE_TESTS) --ignore=tests/estimation/test_kalman_kernel.py --ignore=tests/intake/test_fastread_kernel.py \
		--deselect tests/service/test_health.py::test_packed_check_kernel_refuses_what_it_does_not_take

# pd-web's browser test drives Debian's chromium through chromedriver: installed here when
# missing and possible (root and apt-get); otherwise that test skips and says why.
browser:
	@if [ -x /usr/bin/chromium ] && [ -x /usr/bin/chromedriver ]; then :; \
	elif [ "$$(id -u)" != 0 ]; then \
	  echo "make: chromium for the browser test is missing and only root can install it: that test will skip"; \
	elif ! command -v apt-get >/dev/null; then \
	  echo "make: chromium for the browser test is missing and there is no apt-get: that test will skip"; \
	else \
	  echo "make: installing chromium and chromium-driver (apt-get) for the browser test"; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null) \
	    || echo "make: apt-get could not install chromium: the browser test will skip"; \
	fi

# pd-viz's test with Foxglove's own protocol client (@foxglove/ws-protocol, run in node; the
# version pinned by package-lock.json) installs it here from the npm registry when node and
# npm are there; otherwise that test skips and says why.
VIEWERS := tests/clients/tools/viewers
node-deps:
	@if [ -d $(VIEWERS)/node_modules/@foxglove/ws-protocol ]; then :; \
	elif ! command -v npm >/dev/null; then \
	  echo "make: no npm: the Foxglove protocol client test will skip"; \
	else \
	  echo "make: installing @foxglove/ws-protocol (npm ci in $(VIEWERS)) for the pd-viz client test"; \
	  npm ci --prefix $(VIEWERS) --no-audit --no-fund --silent \
	    || echo "make: npm could not install it: the Foxglove protocol client test will skip"; \
	fi

bench: $(STAMP) native
	$(PY) bench/estimation.py
	$(PY) bench/wire.py

schemas: $(STAMP)
	$(PY) -m pd_service.wire.schemas

# Lint and type check: ruff, then mypy (pydantic plugin; configured in pyproject.toml).
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

clean:
	rm -rf $(VENV) out .pytest_cache .hypothesis

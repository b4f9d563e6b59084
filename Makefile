# Two entry points for a newcomer: `make demo` and `make test`.
# Both create .venv with the project installed; nothing needs installing by hand.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: venv test demo demo-ros2 bench lint schemas clean browser

$(STAMP): pyproject.toml clients/python/pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]' -e 'clients/python[plots,viz]'
	touch $(STAMP)

venv: $(STAMP)

# The demo's PNG plots need matplotlib (the client's `plots` extra), its live view and MCAP
# log foxglove-sdk and mcap (`viz`), both installed above.
demo: $(STAMP)
	$(VENV)/bin/pd-demo

# The ROS 2 variant (rosbags, in the dev extra): docs/ros2.md.
demo-ros2: $(STAMP)
	$(VENV)/bin/pd-demo --ros2

test: $(STAMP) browser
	$(PY) -m pytest -q

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

bench: $(STAMP)
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

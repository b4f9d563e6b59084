# Two entry points for a newcomer: `make demo` and `make test`.
# Both create .venv with the project installed; nothing needs installing by hand.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: venv test demo bench lint schemas clean

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

test: $(STAMP)
	$(PY) -m pytest -q

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

# Thin wrappers around setup.sh and pytest, so a new user needs only `make setup` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stg-setup-done

.PHONY: setup test test-slow test-all lint

setup: $(STAMP)

$(STAMP): pyproject.toml setup.sh
	./setup.sh --venv $(VENV)
	touch $@

# The default suite (slow tests excluded; stays under 15 minutes on a 2-core machine).
test: $(STAMP)
	$(PY) -m pytest $(ARGS)

test-slow: $(STAMP)
	$(PY) -m pytest -m slow $(ARGS)

test-all: $(STAMP)
	$(PY) -m pytest -m "" $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .

# Thin wrappers around setup.sh, the main job and pytest: a new user needs only `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stg-setup-done

.PHONY: setup demo test test-slow test-all lint

setup: $(STAMP)

$(STAMP): pyproject.toml setup.sh
	./setup.sh --venv $(VENV)
	touch $@

# The main job on the embedded default (the open body): `stg-launch launch/demo.yaml`, i.e. a
# synthetic subject generated on the first run, trained online by the node processes, rendered
# to $(DEMO_OUT)/avatar.mp4 and avatar_sheet.png; ends on its own with a summary.
DEMO_OUT ?= runs/demo
DEMO_ARGS ?=
demo: $(STAMP)
	$(VENV)/bin/stg-launch launch/demo.yaml out:=$(DEMO_OUT) $(DEMO_ARGS)
	@echo "==> $(DEMO_OUT)/avatar.mp4, $(DEMO_OUT)/avatar_sheet.png, $(DEMO_OUT)/summary.json"

# The default suite (slow tests excluded; stays under 15 minutes on a 2-core machine).
test: $(STAMP)
	$(PY) -m pytest $(ARGS)

test-slow: $(STAMP)
	$(PY) -m pytest -m slow $(ARGS)

test-all: $(STAMP)
	$(PY) -m pytest -m "" $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .

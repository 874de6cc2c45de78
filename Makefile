# Thin wrappers around setup.sh, the main job and pytest: a new user needs only `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stg-setup-done

.PHONY: setup demo test test-slow test-all test-repeat lint

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

# The default suite N times, with per-test failure counts (tools/test_repeat.py):
#   make test-repeat 5 [BUSY=2] [BACKGROUND=1] [ARGS="tests/nodes"]   (or N=5)
# BUSY=K: the first K runs beside a busy loop; BACKGROUND=K: the last K as a background job.
ifeq (test-repeat,$(firstword $(MAKECMDGOALS)))
  REPEAT_COUNT := $(word 2,$(MAKECMDGOALS))
  ifneq ($(REPEAT_COUNT),)
    $(eval $(REPEAT_COUNT):;@:)
  endif
endif
N ?= $(or $(REPEAT_COUNT),5)
BUSY ?= 0
BACKGROUND ?= 0
test-repeat: $(STAMP)
	$(PY) tools/test_repeat.py $(N) --busy-runs $(BUSY) --background-runs $(BACKGROUND) -- $(ARGS)

test-slow: $(STAMP)
	$(PY) -m pytest -m slow $(ARGS)

test-all: $(STAMP)
	$(PY) -m pytest -m "" $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check stg_node tests tools

# Thin wrappers around setup.sh, the main job and pytest: a new user needs only `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stg-setup-done

.PHONY: setup demo test test-slow test-all lint

setup: $(STAMP)

$(STAMP): pyproject.toml setup.sh
	./setup.sh --venv $(VENV)
	touch $@

# Today's main job on the embedded default (the open body): the synthetic benchmark with ground
# truth that the trainer learns from, plus a contact sheet of it. Becomes `stg-launch
# launch/demo.yaml` once the nodes exist.
DEMO_OUT ?= runs/demo
demo: $(STAMP)
	$(VENV)/bin/stg-synth --out $(DEMO_OUT) --overwrite
	$(PY) tools/synth_montage.py --from $(DEMO_OUT) --out $(DEMO_OUT)/montage.png
	@echo "==> benchmark in $(DEMO_OUT)/ (ZJU-MoCap layout), contact sheet $(DEMO_OUT)/montage.png"

# The default suite (slow tests excluded; stays under 15 minutes on a 2-core machine).
test: $(STAMP)
	$(PY) -m pytest $(ARGS)

test-slow: $(STAMP)
	$(PY) -m pytest -m slow $(ARGS)

test-all: $(STAMP)
	$(PY) -m pytest -m "" $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .

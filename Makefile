# The two set-up commands of README.md: `make demo` (main job on the shipped sample) and `make test`.
# Both create or refresh .venv first (scripts/setup.sh is a no-op when nothing changed).
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: setup demo test

setup:
	@bash scripts/setup.sh

demo: setup
	@bash scripts/demo.sh

test: setup
	@bash scripts/test.sh

# The two commands of the README: `make demo` (the main job) and `make test` (every test).
# Both set everything up on a fresh machine first and are fast when it already is.
SHELL := /bin/bash
.PHONY: setup demo test bench lint lock clean

setup:
	@bash scripts/setup.sh

demo: setup
	@. scripts/env.sh && wheelgrid demo $(ARGS)

test:
	@bash scripts/test.sh $(ARGS)

bench: setup
	@. scripts/env.sh && python bench/run_all.py $(ARGS)

lint: setup
	@. scripts/env.sh && ruff check src test bench conftest.py && ruff format --check src test bench conftest.py && mypy

# A fresh venv each time, removed after: a kept /tmp venv froze whatever an earlier run (or
# another checkout) had installed into it into the lock.
lock:
	@set -o pipefail; tmp=$$(mktemp -d) && trap 'rm -rf "$$tmp"' EXIT \
	  && python3 -m venv "$$tmp/venv" && "$$tmp/venv/bin/pip" install -q -r requirements.in \
	  && "$$tmp/venv/bin/pip" freeze | bash scripts/filter-lock.sh > "$$tmp/lock" \
	  && cp "$$tmp/lock" requirements.lock

clean:
	rm -rf build install log out .stamps

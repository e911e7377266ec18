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
	@. scripts/env.sh && ruff check src test bench && ruff format --check src test bench

lock:
	@python3 -m venv /tmp/wheelgrid-lock-venv && /tmp/wheelgrid-lock-venv/bin/pip install -q -r requirements.in \
	  && /tmp/wheelgrid-lock-venv/bin/pip freeze | bash scripts/filter-lock.sh > requirements.lock

clean:
	rm -rf build install log out .stamps

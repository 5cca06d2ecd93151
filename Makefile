# The README's two commands: `make demo` and `make test`. Each one sets everything up first (idempotent).
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup demo test test-fast typecheck lint docs bench clean certs

setup:
	@bash scripts/setup.sh

demo: setup
	@echo "[demo] running the most complete servo loop available"
	$(VENV)/bin/ddvs demo

test: setup
	@echo "[test] ruff"
	$(VENV)/bin/ruff check .
	@echo "[test] mypy (pyproject.toml, [tool.mypy])"
	$(VENV)/bin/mypy
	@echo "[test] documentation site (mkdocs build --strict: no broken link, no missing page)"
	$(MAKE) --no-print-directory docs
	@echo "[test] pytest (every test, slow ones included; the kernels on Vulkan too: docs/gpu.md)"
	DDVS_REQUIRE_DEVICES=$${DDVS_REQUIRE_DEVICES:-vulkan} $(PY) -m pytest -q

# Your own loop: the same checks without the tests marked slow (a few minutes on 2 cores).
test-fast: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy
	$(PY) -m pytest -q -m "not slow"

typecheck: setup
	$(VENV)/bin/mypy

lint: setup
	$(VENV)/bin/ruff check .

# The documentation site (docs/, mkdocs.yml): regenerate the reference pages from the code (docs/reference/), then
# build it strictly into site/ (open site/index.html). make test runs it: a change to a parser, a setting, a message
# or a docstring shows as a changed page to commit. Not --quiet: it hides the warnings that --strict counts.
export NO_MKDOCS_2_WARNING := 1
docs: setup
	$(PY) -m scripts.docsgen
	$(VENV)/bin/mkdocs build --strict

# The speed benchmarks (benchmarks/README.md): each prints its table with the machine and its load average.
BENCHES ?= bench_registration bench_general bench_global_init
bench: setup
	@for b in $(BENCHES); do echo "[bench] $$b"; $(PY) benchmarks/$$b.py || exit 1; done

# Development CA + per-role TLS certificates for Zenoh (docs/security.md); CERTS_DIR=... to choose where.
CERTS_DIR ?= certs
certs:
	@bash scripts/make_dev_certs.sh $(CERTS_DIR)

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache reports site

# The README's two commands: `make demo` and `make test`. Each one sets everything up first (idempotent).
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup demo test lint bench clean certs

setup:
	@bash scripts/setup.sh

demo: setup
	@echo "[demo] running the most complete servo loop available"
	$(VENV)/bin/ddvs demo

test: setup
	@echo "[test] ruff"
	$(VENV)/bin/ruff check .
	@echo "[test] pytest (every test, slow ones included)"
	$(PY) -m pytest -q

lint: setup
	$(VENV)/bin/ruff check .

bench: setup
	$(VENV)/bin/ddvs bench

# Development CA + per-role TLS certificates for Zenoh (docs/security.md); CERTS_DIR=... to choose where.
CERTS_DIR ?= certs
certs:
	@bash scripts/make_dev_certs.sh $(CERTS_DIR)

clean:
	rm -rf $(VENV) .pytest_cache reports

# Two entry points on a fresh machine:  `make demo`  and  `make test`.
# Both create .venv, fetch wheels into a wheelhouse kept outside the clone (so torch is
# downloaded once per machine), build the Rust extension into a wheel and install it.

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
WHEELHOUSE ?= $(HOME)/.cache/poisson_rs/wheelhouse
SOURCES := $(shell find rust python -type f -not -path '*/__pycache__/*') pyproject.toml Cargo.toml Cargo.lock
OUT ?= out

.PHONY: setup demo test lint rust-test py-test docs bench clean

setup: $(VENV)/.installed

$(VENV)/.deps: requirements.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	mkdir -p $(WHEELHOUSE)
	$(PY) -m pip download --quiet --dest $(WHEELHOUSE) -r requirements.txt
	$(PY) -m pip install --quiet --no-index --find-links $(WHEELHOUSE) -r requirements.txt
	touch $@

$(VENV)/.installed: $(VENV)/.deps $(SOURCES)
	$(PY) -m pip install --quiet --no-deps --no-build-isolation --force-reinstall .
	touch $@

demo: setup
	$(VENV)/bin/poisson-rs demo --out $(OUT)/demo

lint: setup
	$(VENV)/bin/ruff check python tests benches
	$(VENV)/bin/ruff format --check python tests benches
	$(PY) -m mypy
	$(PY) -m mypy.stubtest poisson_rs._core
	cargo fmt --check
	cargo clippy --all-targets --features python -- -D warnings

rust-test:
	cargo test --lib
	cargo test --doc

py-test: setup
	$(PY) -m pytest -q

# The API reference from the docstrings (docs/api/), warnings as errors -> out/api/index.html.
docs: $(VENV)/.deps
	$(PY) -m mkdocs build --strict --quiet -f docs/api/mkdocs.yml

test: lint rust-test py-test docs

bench: setup
	cargo bench --bench rollout
	$(PY) benches/bench_step.py

clean:
	rm -rf $(VENV) target $(OUT)

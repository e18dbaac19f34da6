# twray — every target installs what it needs first (see `install`).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PYTEST_ARGS ?=

.PHONY: install demo test bench bench-generate bench-trace clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

## Main job (until the Table 1 pipeline lands): a birch sample volume and its slice images.
demo: install
	$(BIN)/twray generate --preset birch --size-um 150,150,100 --seed 1 --out results/demo/birch.zarr --overwrite
	$(BIN)/twray slices results/demo/birch.zarr --out results/demo/slices
	@echo "wrote results/demo/birch.zarr and results/demo/slices/*.png"

test: install
	$(BIN)/python -m pytest $(PYTEST_ARGS)

bench: bench-generate bench-trace

bench-generate: install
	$(BIN)/python benchmarks/bench_generate.py --out results/bench.json

clean:
	rm -rf results/demo results/cache

bench-trace: install
	$(BIN)/python benchmarks/bench_trace.py --out results/bench.json

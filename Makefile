# twray — every target installs what it needs first (see `install`).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PYTEST_ARGS ?=
# make test runs the test files on this many processes, each file whole on one (0: in one process).
TEST_WORKERS ?= 2
# quick: the paper's samples, at most 5 woods, a twentieth of the rays (minutes); paper: the committed
# results (SCALE=paper YES=1; Table 1 on as many woods as its target asks for, at most 40: about 40 min on 2 cores);
# small: a tenth of the thickness (tests).
SCALE ?= quick
SCHEDULER ?=
STUDIES := study-1 study-2 study-3 study-4 study-5-1 study-5-2 study-6
EXPERIMENT := birch-0.7mm birch-0.7mm-air balsa-1mm balsa-1mm-air balsa-1mm-radius birch-1mm-fresnel
FIBRE_TIPS := with-ray-cells without-ray-cells
DESIGN := birch birch-air balsa balsa-air
# YES=1 runs what is estimated above TWRAY_CONFIRM_CPU_HOURS.
YES ?=
STUDY_ARGS = --scale $(SCALE) $(if $(SCHEDULER),--scheduler $(SCHEDULER)) $(if $(YES),--yes)
# Each scale has its own results folder: results/paper/ (committed), results/quick/ and results/small/.
RESULTS = results/$(SCALE)

.PHONY: install wheel-check demo test figures report experiment fibre-tips table1-paper-method convergence bench bench-generate bench-trace bench-exact bench-study bench-census bench-table1-paper bench-camera bench-accuracy bench-iso bench-estimates tradeoff clean table1 camera camera-fast design wave bench-wave $(STUDIES)

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

## The wheel, installed into a fresh venv outside the checkout, running generate, trace and a study.
wheel-check:
	./.ci/wheel-check

## Main job: the paper's Table 1 (all studies, `exact`) on a local Dask cluster, cached in results/cache
## (SCALE=quick by default: results/quick/; SCALE=paper YES=1 for the committed results/paper/).
table1: install
	$(BIN)/twray study $(addprefix studies/table1/,$(addsuffix .yaml,$(STUDIES))) $(STUDY_ARGS) --results $(RESULTS) --report $(RESULTS)/table1.md

## The paper's two measured samples (birch 0.7 mm, balsa 1 mm), angles inside and in air -> results/<scale>/experiment/.
experiment: install
	$(BIN)/twray study $(addprefix studies/experiment/,$(addsuffix .yaml,$(EXPERIMENT))) $(STUDY_ARGS) --results $(RESULTS)/experiment --report $(RESULTS)/experiment/haze.md

## Overlapping tapered fibre tips (fibre_tip_um 0-300 µm) with and without ray cells -> results/<scale>/fibre-tips/.
fibre-tips: install
	$(BIN)/twray study $(addprefix studies/fibre-tips/,$(addsuffix .yaml,$(FIBRE_TIPS))) $(STUDY_ARGS) --results $(RESULTS)/fibre-tips --report $(RESULTS)/fibre-tips/fibre-tips.md

## Design maps: haze and FWHM_R of birch and balsa over thickness x ΔRI, inside and in air -> results/<scale>/design/
## (~106 CPU-min at paper scale with `exact`, about an hour on 2 cores), then their figures; `twray design` reads them.
design: install
	$(BIN)/twray study $(addprefix studies/design/,$(addsuffix .yaml,$(DESIGN))) $(STUDY_ARGS) --results $(RESULTS)/design --report $(RESULTS)/design/design.md
	$(BIN)/twray figures --only design --results $(RESULTS) --out $(if $(filter paper,$(SCALE)),results/figures,$(RESULTS)/figures)

## Where geometrical optics holds: `exact` rays against scalar waves (white light) on the same sections over ΔRI
## -> results/<scale>/wave/regime.zarr and its figures (paper scale: about 25 min on 2 cores; quick: a quarter of the thickness).
wave: install
	$(BIN)/twray wave studies/wave/regime.yaml --scale $(SCALE) $(if $(SCHEDULER),--scheduler $(SCHEDULER)) --results $(RESULTS)/wave
	$(BIN)/twray figures --only wave --results $(RESULTS) --out $(if $(filter paper,$(SCALE)),results/figures,$(RESULTS)/figures)

## Table 1 with the paper's method (500 rays per wood) beside `accurate` -> results/<scale>/paper-method/ (~3.5 CPU-h at paper scale).
table1-paper-method: install
	$(BIN)/twray study $(addprefix studies/table1/,$(addsuffix .yaml,$(STUDIES))) $(STUDY_ARGS) --method paper --rays 500 --results $(RESULTS)/paper-method --report $(RESULTS)/paper-method/table1.md

## How far each Table 1 value moves with 4000 rays and with a voxel twice as coarse -> results/convergence.zarr, results/CONVERGENCE.md.
convergence: install
	$(BIN)/python benchmarks/convergence.py --results results

## One row of Table 1, e.g. `make study-2 SCALE=small` or `make study-1 SCHEDULER=tcp://host:8786`.
$(STUDIES): install
	$(BIN)/twray study studies/table1/$@.yaml $(STUDY_ARGS) --results $(RESULTS)

## The paper's Figure 5: images through a TW sheet, traced with `exact` (results/<scale>/camera/): at the
## default SCALE=quick a tenth of the aperture samples (about 10 min on 2 cores); `make camera SCALE=paper YES=1`
## all of them (about 1.5 h on 2 cores); `make camera SCALE=small` a tenth of the samples and a fifth of the sheet.
camera: install
	$(BIN)/twray camera studies/camera/figure5.yaml $(STUDY_ARGS) --results $(RESULTS)/camera

## Figure 5 at full settings traced with `fast` on 0.5 µm voxels (about 3 min on 2 cores; the report sets it
## beside the committed `exact` images) -> results/paper/camera/fast/.
camera-fast: install
	$(BIN)/twray camera studies/camera/figure5.yaml --method fast --results results/paper/camera/fast

## The paper's figures from the committed datasets -> results/figures/ (linked from results/REPORT.md).
figures: install
	$(BIN)/twray figures --results results/paper --out results/figures
	$(BIN)/python benchmarks/bench_tradeoff.py --figure --results results

## The reproduction report, every number read from the committed datasets -> results/REPORT.md.
report: install
	$(BIN)/twray report --results results --scale paper --out results/REPORT.md

## A birch sample volume and its slice images.
demo: install
	$(BIN)/twray generate --preset birch --size-um 150,150,100 --seed 1 --out results/demo/birch.zarr --overwrite
	$(BIN)/twray slices results/demo/birch.zarr --out results/demo/slices
	@echo "wrote results/demo/birch.zarr and results/demo/slices/*.png"

test: install
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

bench: bench-generate bench-trace bench-exact bench-study bench-census bench-camera bench-accuracy bench-iso bench-estimates bench-wave
	$(BIN)/python benchmarks/bench_md.py --bench results/bench.json --out results/BENCH.md

bench-generate: install
	$(BIN)/python benchmarks/bench_generate.py --out results/bench.json

clean:
	rm -rf results/demo results/cache

bench-trace: install
	$(BIN)/python benchmarks/bench_trace.py --out results/bench.json

## `exact` on generated wood: µs/interface beside the voxel methods, 1.5 mm x 1000 rays cold, refinement.
bench-exact: install
	$(BIN)/python benchmarks/bench_exact.py --out results/bench.json

## Every command's CPU, memory and disk estimate beside what it used -> results/estimates.md and the guided rays' tiles -> results/guided_tiles.json (about 9 min).
bench-estimates: install
	$(BIN)/python benchmarks/bench_estimates.py --paper --out results/bench.json
	$(BIN)/python benchmarks/guided_tiles.py --out results/guided_tiles.json

bench-study: install
	$(BIN)/python benchmarks/bench_study.py --out results/bench.json

## Where study 1's `exact` time goes at paper scale, counted inside the workers (tiles, regions, the march and
## its evaluations by purpose; about 8 min on 2 cores) -> results/bench.json.
bench-census: install
	$(BIN)/python benchmarks/study_census.py studies/table1/study-1.yaml --scale paper --out results/bench.json

## Table 1 at paper scale, cold in a fresh cache (20-30 min on 2 cores) -> results/bench.json (REPORT.md's cost).
bench-table1-paper: install
	$(BIN)/python benchmarks/bench_study.py --paper --out results/bench.json

## The wave solver's cost per case beside `exact`, its convergence in dx and dz and its precision (about 4 min).
bench-wave: install
	$(BIN)/python benchmarks/bench_wave.py --out results/bench.json

bench-camera: install
	$(BIN)/python benchmarks/bench_camera.py --out results/bench.json

## Every method against exact optics of many thin walls -> results/accuracy.json and results/accuracy.md.
bench-accuracy: install
	$(BIN)/python benchmarks/bench_accuracy.py --out results/accuracy.json

## Grey-level scans traced with iso, and binarised with accurate and fast, beside exact on the same wood and rays
## (birch 0.25 mm at 1, 0.5 and 0.25 µm and birch 1 mm at 1 and 0.5 µm, clean and blurred+noisy;
## balsa 1 mm at 1 µm, clean; 5 woods x 4000 rays each;
## scans generated where the rays read them; the reference lattices of results/accuracy.md as grey scans)
## -> results/iso*.json, results/iso.md and the scans' section of results/accuracy.md (about 6 hours on 2 cores).
ISO_1MM = --thickness-mm 1 --scans clean --side-um 800 --beam-um 100 --rays 4000 --out results/iso.json
bench-iso: install
	$(BIN)/python benchmarks/bench_iso.py --preset birch --thickness-mm 0.25 --voxels 1,0.5,0.25 --rays 4000 --out results/iso.json
	$(BIN)/python benchmarks/bench_iso.py --preset birch $(ISO_1MM) --voxels 1,0.5
	$(BIN)/python benchmarks/bench_iso.py --preset birch --thickness-mm 1 --voxels 1 --scans "blur 0.3 µm + noise 0.02" --side-um 800 --beam-um 100 --rays 4000 --merge --out results/iso.json
	$(BIN)/python benchmarks/bench_iso.py --preset birch --thickness-mm 1 --voxels 0.5 --scans "blur 0.3 µm + noise 0.02" --side-um 800 --beam-um 100 --rays 4000 --methods "iso,iso smoothed 0.5 µm,accurate" --cache-mb 5000 --merge --out results/iso.json
	$(BIN)/python benchmarks/bench_iso.py --preset balsa $(ISO_1MM) --voxels 1
	$(BIN)/python benchmarks/iso_normals.py results/iso_normals.json
	$(BIN)/python benchmarks/bench_iso.py --preset birch --thickness-mm 0.25 --voxels 0.5 --scans clean --rays 4000 --woods 25 --methods iso,accurate --out results/iso_25woods.json
	$(BIN)/python benchmarks/bench_iso.py --preset birch --thickness-mm 0.25 --voxels 0.5 --scans clean --rays 4000 --woods 25 --methods "iso smoothed 0.5 µm" --merge --out results/iso_25woods.json
	$(BIN)/python benchmarks/bench_iso.py --lattices --out results/iso.json --md results/iso.md
	$(BIN)/python benchmarks/bench_accuracy.py --render

## Speed against accuracy of every setting, on lattices and on the wood against `exact` -> results/tradeoff.zarr,
## results/TRADEOFF.md, results/figures/tradeoff.png and the wood section of results/accuracy.md.
tradeoff: install
	$(BIN)/python benchmarks/bench_tradeoff.py --results results
	$(BIN)/python benchmarks/bench_accuracy.py --render --out results/accuracy.json

# scenegen developer commands. `make demo` and `make test` each set up .venv first (idempotent).
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
# test processes (pytest-xdist, one test file per process at a time): CI's 2 cores
TEST_WORKERS ?= 2
PYTEST_FILES_AT_ONCE = $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile
export MUJOCO_GL ?= egl

.PHONY: setup install-exporters browser demo robosuite-objects generator-grocery bench-user-assets test test-fast test-full fuzz kill bench-soak audit lint assets bench bench-rare bench-requests bench-null bench-proposer bench-repair bench-realism bench-env bench-primitives bench-physics bench-stereo bench-audit bench-start sweep transfer clean

$(BIN)/scenegen: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev,export,ray]'
	touch $@

setup: $(BIN)/scenegen  ## create .venv with pinned dependencies (torch 2.13.0 CPU, mujoco 3.3.7, robosuite 1.5.2, ray 2.60.0)

# lerobot (the LeRobot exporter) cannot be a pip extra: it declares torch<2.11 and diffusers<0.36, so
# it goes in with --no-deps beside the tested versions of what its dataset code imports
# (constraints/exporters.txt); `pip check` may then list only lerobot's own declarations.
$(VENV)/.exporters: constraints/exporters.txt $(BIN)/scenegen
	$(BIN)/pip install --quiet -c constraints/exporters.txt datasets av accelerate torchvision
	$(BIN)/pip install --quiet -c constraints/exporters.txt --no-deps lerobot
	! $(BIN)/pip check | grep -v '^lerobot 0\.4\.4 '
	$(BIN)/python -c "from scenegen.export.lerobot import lerobot_version; print('lerobot', lerobot_version())"
	touch $@

install-exporters: $(VENV)/.exporters  ## the LeRobot exporter (lerobot 0.4.4, dataset format v3.0) beside the project's pins

demo: setup  ## generate and render the demo batch into runs/demo (replaces an earlier one), its contact sheet, audit and report
	rm -rf runs/demo
	$(BIN)/scenegen generate pipelines/demo.yaml --out runs/demo --workers 2
	$(BIN)/scenegen show runs/demo
	$(BIN)/scenegen audit runs/demo/manifest.yaml
	$(BIN)/scenegen report runs/demo --quiet --workers 2  # prints its path: open it in a browser

# Debian's chromium for the report's browser test (Playwright drives it; its own download fails here)
browser:  ## install chromium with apt when it is missing (sudo when not root)
	command -v chromium >/dev/null || { SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq chromium; }

ROBOSUITE_OBJECTS = $(shell $(BIN)/python -c "import robosuite, os; print(os.path.dirname(robosuite.__file__))" 2>/dev/null)/models/assets
RS_CATALOG = runs/robosuite_objects/catalog.yaml
RS_ADD = $(BIN)/scenegen assets add --category grocery --catalog $(RS_CATALOG)

robosuite-objects: setup  ## import robosuite's six object meshes as a user catalog, generate a batch with them, audit it (docs/assets.md)
	rm -rf runs/robosuite_objects runs/robosuite_batch
	$(RS_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/bottle.obj --name rs_bottle --mass 0.3 --texture $(ROBOSUITE_OBJECTS)/textures/glass.png
	$(RS_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/bread.obj --name rs_bread --mass 0.1 --texture $(ROBOSUITE_OBJECTS)/textures/bread.png
	$(RS_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/can.obj --name rs_can --mass 0.35 --texture $(ROBOSUITE_OBJECTS)/textures/soda.png
	$(RS_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/cereal.obj --name rs_cereal --mass 0.4 --texture $(ROBOSUITE_OBJECTS)/textures/cereal.png
	$(RS_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/lemon.obj --name rs_lemon --mass 0.1 --texture $(ROBOSUITE_OBJECTS)/textures/lemon.png
	$(RS_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/milk.obj --name rs_milk --mass 0.5 --texture $(ROBOSUITE_OBJECTS)/textures/ceramic.png
	$(BIN)/scenegen assets show rs_bottle rs_bread rs_can rs_cereal rs_lemon rs_milk --catalog $(RS_CATALOG) --out runs/robosuite_objects/asset_sheet.png
	$(BIN)/scenegen generate pipelines/robosuite_objects.yaml --out runs/robosuite_batch --workers 2
	$(BIN)/scenegen show runs/robosuite_batch
	$(BIN)/scenegen audit runs/robosuite_batch/manifest.yaml

RK_CATALOG = runs/robosuite_known/catalog.yaml
RK_ADD = $(BIN)/scenegen assets add --catalog $(RK_CATALOG)

generator-grocery: robosuite-objects  ## a generator that knows the category grocery: 2,000 reference layouts, then training (~50 min; docs/assets.md)
	$(BIN)/scenegen reference pipelines/reference_grocery.yaml --out runs/reference_grocery.parquet --workers 2
	$(BIN)/scenegen train --data runs/reference_grocery.parquet --out runs/generator_grocery

bench-user-assets: setup  ## user assets with the generator: known categories; a new one too with CHECKPOINT=runs/generator_grocery (docs/assets.md)
	rm -rf runs/robosuite_known
	$(RK_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/can.obj --category can --name rs_can --mass 0.35 --texture $(ROBOSUITE_OBJECTS)/textures/soda.png
	$(RK_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/bottle.obj --category bottle --name rs_bottle --mass 0.3 --texture $(ROBOSUITE_OBJECTS)/textures/glass.png
	$(RK_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/cereal.obj --category box --name rs_cereal --mass 0.4 --texture $(ROBOSUITE_OBJECTS)/textures/cereal.png
	$(RK_ADD) $(ROBOSUITE_OBJECTS)/objects/meshes/milk.obj --category box --name rs_milk --mass 0.5 --texture $(ROBOSUITE_OBJECTS)/textures/ceramic.png
	$(BIN)/python benchmarks/user_assets.py --n 30 $(if $(CHECKPOINT),--checkpoint $(CHECKPOINT))

test: setup install-exporters browser  ## the whole test suite, as CI runs it (exporters included; TEST_WORKERS=2 files at a time)
	$(PYTEST_FILES_AT_ONCE) --durations=25

test-fast: setup install-exporters browser  ## everything but the slow end-to-end tests
	$(PYTEST_FILES_AT_ONCE) -m "not slow"

test-full: setup  ## the full-size regenerations (the committed reference set, bit for bit; ~50 min)
	$(BIN)/python -m pytest -q --full -m full

fuzz: setup  ## the long fuzzing profile: 1,000 examples per input kind through the CLI (tests/fuzz; report in runs/fuzz/report.json)
	mkdir -p runs/fuzz
	SCENEGEN_FUZZ=long SCENEGEN_FUZZ_REPORT=runs/fuzz/report.json $(BIN)/python -m pytest -q -p no:cacheprovider tests/fuzz

audit: setup  ## verify data_manifest.yaml against the files (scenegen audit)
	$(BIN)/scenegen audit data_manifest.yaml

lint: setup
	$(BIN)/ruff check scenegen tests benchmarks
	$(BIN)/ruff format --check scenegen tests benchmarks

bench: setup  ## pipeline throughput: baseline commit vs this checkout, 1 and 2 workers, Ray (benchmarks/pipeline_throughput.py, ~10 min)
	$(BIN)/python benchmarks/pipeline_throughput.py

bench-soak: setup  ## memory over a long batch: 3,000 scenes without rendering, 500 with, RSS every 100 (benchmarks/soak.py, ~30 min)
	$(BIN)/python benchmarks/soak.py

kill: setup  ## the kill harness in full: 20 random SIGKILLs per command, 5 for the tiny transfer experiment (tests/kill, <= 60 min)
	mkdir -p runs/kill
	SCENEGEN_KILL_POINTS=20 SCENEGEN_KILL_TRANSFER_POINTS=5 SCENEGEN_KILL_REPORT=runs/kill/report.json $(BIN)/python -m pytest -q -p no:cacheprovider tests/kill

bench-rare: setup  ## rare-case yield per CPU-second per tag: both baselines and the generator (benchmarks/rare_case_yield.py)
	$(BIN)/python benchmarks/rare_case_yield.py

bench-requests: setup  ## drawn requests nobody tuned for, every proposer, tries and CPU-s per scene: the tuning half (benchmarks/request_suite.py; 90 batches of up to 300 tries: hours)
	$(BIN)/python benchmarks/request_suite.py

bench-null: setup  ## 2,000 null-condition scenes of the generator against the held-out reference (benchmarks/null_condition.py)
	$(BIN)/python benchmarks/null_condition.py

bench-proposer: setup  ## the proposer's own CPU per proposal, baseline commit vs this checkout, same proposals (benchmarks/proposer_cpu.py, ~3 min)
	$(BIN)/python benchmarks/proposer_cpu.py

bench-repair: setup  ## multi-tag requests: tries and CPU per accepted scene, baseline vs v2 cost terms without and with repairs (benchmarks/repair_yield.py, ~20 min)
	$(BIN)/python benchmarks/repair_yield.py

bench-env: setup  ## environment reset and step costs, with and without a camera (benchmarks/env_step.py)
	$(BIN)/python benchmarks/env_step.py

bench-primitives: setup  ## CPU-s per labelled scene and per closed-loop episode, baseline commit vs this checkout, outcomes compared bit for bit (benchmarks/primitives.py, ~15 min)
	$(BIN)/python benchmarks/primitives.py

bench-physics: setup  ## cheaper physics for the control loop: each lever's CPU per labelled scene and outcomes against the stored labels, paired by layout (benchmarks/physics_screen.py; 100 layouts, hours: SETTINGS=dt5,hull LAYOUTS=20 for less)
	$(BIN)/python benchmarks/physics_screen.py $(if $(SETTINGS),--settings $(SETTINGS)) $(if $(LAYOUTS),--layouts $(LAYOUTS))

bench-stereo: setup  ## the simulated active stereo sensor against a D415's figures (plane RMS, fill, edge bands), per category, CPU per frame (benchmarks/stereo_sensor.py, ~3 min)
	$(BIN)/python benchmarks/stereo_sensor.py

bench-audit: setup  ## the audit of a 3,000-scene rendered batch, baseline commit vs this checkout, 1 and 2 workers (benchmarks/audit_scale.py; generating the batch ~30 min the first time)
	$(BIN)/python benchmarks/audit_scale.py

bench-start: setup  ## the whole demo process (48 scenes, 2 workers) against the baseline commit's batch loop (benchmarks/start_finish.py, ~4 min)
	$(BIN)/python benchmarks/start_finish.py

bench-realism: setup  ## batch realism checks of the generator at w = 1 and w = 4 (benchmarks/realism_guidance.py)
	$(BIN)/python benchmarks/realism_guidance.py

transfer: setup  ## the transfer experiment, version 2's declared run (pipelines/transfer.yaml; docs/transfer.md; hours, resumable): assets/transfer/v2/result
	$(BIN)/scenegen experiment transfer

sweep: setup  ## guidance sweep of the generator: runs/sweep/sweep.{md,png,json}
	$(BIN)/scenegen sweep --workers 2

assets: setup  ## rebuild assets/ (meshes, convex parts, catalog); coacd runs only for changed meshes
	$(BIN)/python -m scenegen.assets.authoring

clean:
	rm -rf runs .pytest_cache

# Two commands do everything on a fresh machine:  make demo  and  make test.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
TORCH_VERSION := 2.14.1
TORCHVISION_VERSION := 0.29.1
EXTRAS := dev,ray,minari,multi,sb3,docs,video
#: Test processes, a core each (the suite's tests are single-threaded; each holds PyTorch).
TEST_WORKERS ?= 2
export MUJOCO_GL ?= egl

.PHONY: setup demo demo-summary test test-slow lint docs bench clean

setup: .sysdeps-stamp $(VENV)/.setup-stamp

.sysdeps-stamp: scripts/install_system_deps.sh
	bash scripts/install_system_deps.sh
	touch $@

$(VENV)/.setup-stamp: pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==$(TORCH_VERSION) torchvision==$(TORCHVISION_VERSION)
	$(BIN)/python -m pip install --quiet -e ".[$(EXTRAS)]"
	touch $@

# Each demo stage runs through $(call stage,NAME,COMMAND), which appends "NAME SECONDS" to
# $(TIMINGS); the demo ends with what it wrote under results/ and the time per stage.
RESULTS := results
TIMINGS := $(RESULTS)/demo_timings.txt
stage = @echo "== $(1): $(strip $(2))" && start=$$(date +%s) && $(2) && \
	echo "$(1) $$(( $$(date +%s) - start ))" >> $(TIMINGS)

demo: setup
	mkdir -p $(RESULTS)
	rm -f $(RESULTS)/results.jsonl && echo "started $$(date +%s)" > $(TIMINGS)
	$(call stage,raceline,$(BIN)/saferace raceline technical \
		--out results/technical_raceline.csv --plot results/technical_raceline.png)
	$(call stage,eval-expert,$(BIN)/saferace eval --agent expert --task CenterLine --track technical \
		--out results/results.jsonl && $(BIN)/saferace eval --agent expert --task RacingLine \
		--track technical --out results/results.jsonl)
	$(call stage,leaderboard,$(BIN)/saferace leaderboard results/results.jsonl \
		--plot results/trajectories.png)
	$(call stage,drive-video,$(BIN)/saferace drive --agent expert --task RacingLine --track technical \
		--video results/technical_racingline.mp4 --rerun results/technical_racingline.rrd)
	$(call stage,overtake,$(BIN)/saferace drive --agent expert --task Overtake --track technical \
		--laps 2 --video results/technical_overtake.mp4 --rerun results/technical_overtake.rrd)
	$(call stage,snapshots,$(BIN)/saferace snapshots --out results/snapshots)
	$(call stage,perception,$(BIN)/saferace perception --workers 2)
	$(call stage,safety-table,$(BIN)/saferace safety-table --random-tracks 11 23 --out results/safety)
	rm -rf results/learned
	$(call stage,collect,$(BIN)/saferace collect --agent expert --task CenterLine --track lab --laps 3 \
		--seeds 0 1 2 3 4 5 --perturb 0.05 --out results/learned/data && \
		$(BIN)/saferace collect --agent expert --task CenterLine --track lab --laps 3 \
		--seeds 100 --out results/learned/data)
	$(call stage,train,$(BIN)/saferace train results/learned/data --augment --early-stop 3 \
		--out results/learned/lab_mono.pt)
	$(call stage,eval-learned,$(BIN)/saferace eval --agent learned:results/learned/lab_mono.pt \
		--task CenterLine --track lab --laps 3 --out results/learned/eval.jsonl)
	$(call stage,gradcam,$(BIN)/saferace gradcam results/learned/lab_mono.pt --track lab \
		--out results/learned/gradcam)
	$(call stage,paper-tables,$(BIN)/saferace paper-tables --preset quick --out results/paper)
	@$(MAKE) --no-print-directory demo-summary

# What the last demo wrote under $(RESULTS) (files no older than the start in $(TIMINGS); a
# dataset's round folders, or a folder of more than 8 files, as one line with their count and
# size) and the seconds per stage. Runs alone too: make demo-summary [RESULTS=folder]

demo-summary:
	@$(BIN)/python scripts/demo_summary.py $(RESULTS)

test: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy saferace
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=15

test-slow: setup
	bash scripts/install_chromium.sh
	$(BIN)/python -m pytest -q -m slow --durations=15

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy saferace

docs: setup
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

bench: setup
	$(BIN)/python -m pip install --quiet -e ".[dev,bench]"
	$(BIN)/python benchmarks/raceline_speed.py
	$(BIN)/python benchmarks/frenet_speed.py
	$(BIN)/python benchmarks/mpc_speed.py
	$(BIN)/python benchmarks/env_speed.py
	$(BIN)/python benchmarks/traffic_speed.py
	$(BIN)/python benchmarks/learned_step_speed.py
	$(BIN)/python benchmarks/benchmark_scaling.py

clean:
	rm -rf $(VENV) .sysdeps-stamp results site

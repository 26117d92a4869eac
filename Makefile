# Two commands do everything on a fresh machine:  make demo  and  make test.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
TORCH_VERSION := 2.14.1
TORCHVISION_VERSION := 0.29.1
export MUJOCO_GL ?= egl

.PHONY: setup demo test test-slow lint bench clean

setup: .sysdeps-stamp $(VENV)/.setup-stamp

.sysdeps-stamp: scripts/install_system_deps.sh
	bash scripts/install_system_deps.sh
	touch $@

$(VENV)/.setup-stamp: pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==$(TORCH_VERSION) torchvision==$(TORCHVISION_VERSION)
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	touch $@

demo: setup
	mkdir -p results
	$(BIN)/saferace raceline technical --out results/technical_raceline.csv --plot results/technical_raceline.png
	rm -f results/results.jsonl
	$(BIN)/saferace eval --agent expert --task CenterLine --track technical --out results/results.jsonl
	$(BIN)/saferace eval --agent expert --task RacingLine --track technical --out results/results.jsonl
	$(BIN)/saferace leaderboard results/results.jsonl --plot results/trajectories.png
	$(BIN)/saferace drive --agent expert --task RacingLine --track technical \
		--video results/technical_racingline.mp4 --rerun results/technical_racingline.rrd
	$(BIN)/saferace snapshots --out results/snapshots
	$(BIN)/saferace safety-table --random-tracks 11 23 --out results/safety
	rm -rf results/learned
	$(BIN)/saferace collect --agent expert --task CenterLine --track lab --laps 3 \
		--seeds 0 1 2 3 4 5 --perturb 0.05 --out results/learned/data
	$(BIN)/saferace collect --agent expert --task CenterLine --track lab --laps 3 \
		--seeds 100 --out results/learned/data
	$(BIN)/saferace train results/learned/data --out results/learned/lab_mono.pt
	$(BIN)/saferace eval --agent learned:results/learned/lab_mono.pt --task CenterLine \
		--track lab --laps 3 --out results/learned/eval.jsonl
	$(BIN)/saferace gradcam results/learned/lab_mono.pt --track lab --out results/learned/gradcam
	$(BIN)/saferace paper-tables --preset quick --out results/paper

test: setup
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

test-slow: setup
	bash scripts/install_chromium.sh
	$(BIN)/python -m pytest -q -m slow

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python -m pip install --quiet -e ".[dev,bench]"
	$(BIN)/python benchmarks/raceline_speed.py
	$(BIN)/python benchmarks/frenet_speed.py
	$(BIN)/python benchmarks/mpc_speed.py
	$(BIN)/python benchmarks/env_speed.py
	$(BIN)/python benchmarks/learned_step_speed.py
	$(BIN)/python benchmarks/benchmark_scaling.py

clean:
	rm -rf $(VENV) .sysdeps-stamp results

# lidarops. `make` (= make build) compiles the extension and installs lidarops, editable, into the
# environment it uses; then `source .venv/bin/activate` (when make created .venv) puts python with
# lidarops and the lidarops command on your path. Times: this project's 2-core CPU machines.
#
# make build       environment, compile (clean: about 2 min, 28 files; nothing changed: seconds; the
#                  compiler's output goes to build/build.log), editable install (seconds, no recompile)
# make demo        build, then the main job on built-in synthetic data (about 2 min): simulated LiDAR
#                  streams through streaming pillarization, the PFN and the SSCATeR backbone, checked
#                  against full recomputation (lidarops stream; writes lidarops_stream_<scenario>.png),
#                  then the shipped PointPillars on 40 unseen simulated frames, scored (lidarops detect)
# make test        build, then the whole test suite in TEST_JOBS processes (pytest-xdist; a dot per test,
#                  and a line naming what runs when no test has finished for 45 s; what CI runs; about 7.5 min)
# make test-fast   build, then the suite without the tests marked slow (-m "not slow"; under 2 min)
# make fuzz        build, then the fuzz suite tests/fuzz with its long profile (HYPOTHESIS_PROFILE=long:
#                  2,000 random examples per test, each test once per device; about 25 min on 2 CPU cores,
#                  more with CUDA); failures are kept in .hypothesis/ and replayed first (CONTRIBUTING.md, "Testing")
# make tour        the short tour of the neighbourhood ops (lidarops tour)
# make bench       the neighbourhood-op benchmarks (benchmarks/bm_neighbors.py)
# make train-demo  simulate a small KITTI-format set and train a Car-only PointPillars on it (CPU, ~5 min)
# make clean       remove build/ and the compiled library (make build restores both)
# make help        this text
#
# Uses the python3 that already has torch (the GPU machine: torch + nvcc preinstalled, offline);
# otherwise creates .venv and installs the CPU torch wheel there. Variables: PYTHON, VENV,
# MAX_JOBS (compile jobs; default: every core), PYTEST_ARGS (e.g. PYTEST_ARGS="-x -k knn").
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(shell if $(PYTHON) -c "import torch" >/dev/null 2>&1; then command -v $(PYTHON); else echo $(abspath $(VENV))/bin/python; fi)
PYTEST_ARGS ?=
# the suite runs in TEST_JOBS processes (pytest-xdist; default: the cores, at most 8); TEST_JOBS=1 runs it in one
# process, a line per file
TEST_JOBS ?= $(shell n=$$(nproc 2>/dev/null || echo 1); [ $$n -gt 8 ] && n=8; echo $$n)
XDIST = $(shell [ "$(TEST_JOBS)" -gt 1 ] 2>/dev/null && $(PY) -c "import xdist" >/dev/null 2>&1 && echo "-n $(TEST_JOBS) --dist worksteal ")
.DEFAULT_GOAL := build

.PHONY: help env build test test-fast fuzz demo tour bench clean train-demo

help:
	@awk '/^#/ { sub(/^# ?/, ""); print; next } { exit }' $(firstword $(MAKEFILE_LIST))

env:
	@if [ ! -x "$(PY)" ]; then echo "[make] environment: creating $(VENV) ($$($(PYTHON) --version 2>&1))"; $(PYTHON) -m venv $(VENV); fi
	@$(PY) tools/ensure_env.py

build: env
	@$(PY) tools/build.py

test: build
	@echo "[make] tests: pytest $(XDIST)$(if $(PYTEST_ARGS),$(PYTEST_ARGS) )tests (the whole suite; a dot per test)"
	@$(PY) -m pytest $(XDIST)$(PYTEST_ARGS) tests

test-fast: build
	@echo "[make] tests: pytest -m \"not slow\" $(XDIST)$(if $(PYTEST_ARGS),$(PYTEST_ARGS) )tests (a dot per test)"
	@$(PY) -m pytest -m "not slow" $(XDIST)$(PYTEST_ARGS) tests

fuzz: build
	@echo "[make] fuzz: HYPOTHESIS_PROFILE=long pytest $(if $(PYTEST_ARGS),$(PYTEST_ARGS) )tests/fuzz"
	@HYPOTHESIS_PROFILE=long $(PY) -m pytest $(PYTEST_ARGS) tests/fuzz

# about a minute on 2 CPU cores after the build: three short SSCATeR streams (each run explains what it
# shows), then the shipped detector on three unseen frames
demo: build
	@echo "[demo] SSCATeR 1/3: the shipped PointPillars streaming driving_city: boxes every 10 ms from a map recycled from"
	@echo "       the last step (only the pillars that changed are recomputed), checked against the detector on the same window"
	$(PY) -m lidarops stream --checkpoint shipped --scenario driving_city --seconds 0.15 --check-every 5
	@echo "[demo] SSCATeR 2/3: the shipped Aerial-PointPillars streaming drone_bridge (a rosette-scan LiDAR on a drone, the"
	@echo "       simulator's avia profile: quadcopters, a Livox Avia's reflectivity): drones found every 10 ms; the scan"
	@echo "       changes pillars all over the view, so there is less to recycle"
	$(PY) -m lidarops stream --checkpoint aerial_pointpillars --scenario drone_bridge --realism avia --seconds 0.2 --check-every 10
	@echo "[demo] SSCATeR 3/3: the random-weights benchmark mode on the same stream, with 90 % ReLU zeros (sparser"
	@echo "       activations stop the change spreading)"
	$(PY) -m lidarops stream --scenario drone_bridge --realism avia --seconds 1.5 --relu-zeros 0.9 --out lidarops_stream_drone_bridge_relu90.png
	@echo "[demo] detection: the shipped PointPillars (lidarops/weights) on 40 simulated frames it never saw: boxes,"
	@echo "       a bird's-eye view (demo_detections/*.png), ms per frame, KITTI 3D AP beside the trained model's, found / labelled"
	$(PY) -m lidarops detect --scenario driving_city --frames 40 --seed 2026 --out demo_detections --print-frames 1 --print-boxes 5
	@echo "[demo] queries (CounterNet): an index of 12 simulated frames counted twice, by the labels and by the shipped"
	@echo "       PointPillars as a counter; one query of each type, the detector's answer beside the labels' (demo_index/)"
	$(PY) -m lidarops index build --scenario driving_city --frames 12 --out demo_index --no-progress
	$(PY) -m lidarops index build --scenario driving_city --frames 12 --out demo_index --source detector --no-progress
	$(PY) -m lidarops query retrieve demo_index --where "Car>=5" --where "Pedestrian<=3" --compare --html demo_index/answer.html
	$(PY) -m lidarops query count demo_index --where "Pedestrian>=2" --compare
	$(PY) -m lidarops query sum demo_index --class Car --compare
	@echo "[demo] CounterNet: the shipped counter (lidarops/weights/counternet_road7, seven road classes) on 4 dense frames of the"
	@echo "       simulator's realism profile it never saw, its counts beside the labels, and its answers to two queries (demo_counter_index/)"
	$(PY) -m lidarops index build --scenario driving_city --object-counts dense --realism kitti --frames 4 --out demo_counter_index --no-progress --classes Car Truck Bus Pedestrian Cyclist Barrier TrafficCone
	$(PY) -m lidarops index build --scenario driving_city --object-counts dense --realism kitti --frames 4 --out demo_counter_index --no-progress --source counter
	$(PY) -m lidarops query retrieve demo_counter_index --where "Car>=1" --counts
	$(PY) -m lidarops query retrieve demo_counter_index --where "Pedestrian>=3" --compare
	$(PY) -m lidarops query sum demo_counter_index --class Car --compare
	@echo "[demo] samplers: the detector on one unseen frame keeping 1 point in 8, by random sampling, by farthest point"
	@echo "       sampling and by the shipped CAS-Net (casnet_pointpillars_d8, about 20 s on 2 cores); boxes in demo_detections/*_d8/"
	$(PY) -m lidarops detect --scenario driving_city --frames 1 --seed 2026 --out demo_detections/random_d8 --print-frames 1 --print-boxes 3 --sampler random --ratio 8
	$(PY) -m lidarops detect --scenario driving_city --frames 1 --seed 2026 --out demo_detections/fps_d8 --print-frames 1 --print-boxes 3 --sampler fps --ratio 8
	$(PY) -m lidarops detect --scenario driving_city --frames 1 --seed 2026 --out demo_detections/casnet_d8 --print-frames 1 --print-boxes 3 --sampler casnet --ratio 8

train-demo: build
	@echo "[train-demo] a Car-only PointPillars on 120 simulated frames (seed 100), 6 epochs on the CPU: about 5 minutes on"
	@echo "             2 cores; expect a Car BEV AP of 20-40 and a low 3D AP on 25 frames it never saw (configs/pointpillars/pointpillars_demo.yaml)"
	$(PY) -m lidarops data synth --scenario driving_city --frames 150 --val-fraction 0.2 --seed 100 --workers 2 --out data/synth_demo
	$(PY) -m lidarops train --config pointpillars_demo --data data/synth_demo --out runs/demo --workers 2 --eval-every 0
	$(PY) -m lidarops detect --scenario driving_city --frames 25 --checkpoint runs/demo/final.pth --out runs/demo/detections --print-frames 1 --print-boxes 5

tour: build
	$(PY) -m lidarops tour

bench: build
	$(PY) benchmarks/bm_neighbors.py

clean:
	rm -rf build lidarops/_C*.so lidarops/_C*.so.*.tmp lidarops/_build_info.json

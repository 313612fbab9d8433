# make demo   build everything and run the main job on built-in synthetic data: simulated LiDAR streams
#             through streaming pillarization, the PFN and the SSCATeR backbone, checked against full
#             recomputation (lidarops stream; writes lidarops_stream_<scenario>.png)
# make test   build everything and run the test suite
# make tour   the short tour of the neighbourhood ops (lidarops tour)
# make train-demo  simulate a small KITTI-format set and train a small PointPillars on it (CPU, minutes)
#
# Uses the python3 that already has torch (the GPU machine: torch + nvcc preinstalled, offline);
# otherwise creates .venv and installs the CPU torch wheel there.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(shell if $(PYTHON) -c "import torch" >/dev/null 2>&1; then command -v $(PYTHON); else echo $(abspath $(VENV))/bin/python; fi)
PYTEST_ARGS ?= -q

.PHONY: env build test demo tour bench clean train-demo

env:
	@if [ ! -x "$(PY)" ]; then echo "[make] creating $(VENV)"; $(PYTHON) -m venv $(VENV); fi
	@$(PY) tools/ensure_env.py

build: env
	$(PY) setup.py -q build_ext --inplace

test: build
	$(PY) -m pytest $(PYTEST_ARGS) tests

# on CPU lidarops stream picks its narrow network (--small) unless --full-size is given: ~2 minutes on 2 CPU cores
demo: build
	$(PY) -m lidarops stream --scenario drone_bridge --seconds 5
	$(PY) -m lidarops stream --scenario driving_city --seconds 1
	@echo "[demo] the shipped PointPillars (lidarops/weights) on 3 simulated frames it never saw: boxes, a"
	@echo "       bird's-eye view with detections and labels (demo_detections/*.png), and KITTI AP of the 3 frames"
	$(PY) -m lidarops detect --scenario driving_city --frames 3 --seed 2026 --out demo_detections --print-frames 1

train-demo: build
	$(PY) -m lidarops data synth --scenario driving_city --frames 60 --val-fraction 0.2 --workers 2 --out data/synth_demo
	$(PY) -m lidarops train --config configs/pointpillars_demo.yaml --data data/synth_demo --out runs/demo --epochs 4 --workers 2

tour: build
	$(PY) -m lidarops tour

bench: build
	$(PY) benchmarks/bm_neighbors.py

clean:
	rm -rf build lidarops/_C*.so lidarops/_build_info.json

# Set-up and the two main commands. `make demo` runs the main job on a small CPU default, each long
# step with a progress bar (generate, train and evaluate; `--quiet` is for logs); `make test` runs
# the test suite and lists its 15 slowest tests. Both create the virtualenv on first use.
VENV ?= .venv
PY := $(VENV)/bin/python
# CPU build of torch (the learn extra), installed first so that the extra finds it; on a GPU
# machine use e.g. TORCH_SPEC="torch" (CUDA build).
TORCH_SPEC ?= torch==2.13.0
OUT ?= out
DEVICE ?= cpu
# The demo's size: a small multipath dataset and a few CPU minutes of training (a smoke run), and a
# fresh drive (suite seed 2026: scenes neither model saw) on which the shipped pretrained model, the
# smoke run and the study's K = 5 and memory models are scored side by side, with the occupancy grids.
DEMO_FRAMES ?= 300
DEMO_DRIVE_FRAMES ?= 200
DEMO_TRAIN ?= --epochs 4 --lr 2e-3 --loss bce --val-fraction 0.34 --overwrite
PRETRAINED ?= learn/pretrained/polar_unet_k5.pt
# issue 39's study, seed 0 (randomised suite, 3 bounces): K = 5 and the model with memory of the drive
MEMORY ?= learn/pretrained/polar_memory_k5.pt
K5_RANDOMISED ?= learn/pretrained/polar_unet_k5_randomised.pt

.PHONY: demo test lint system-deps clean

# Set-up says what it installs, and pip shows each package and download as it goes.
$(VENV)/.installed: pyproject.toml
	@$(MAKE) --no-print-directory system-deps
	@echo "set-up (once): a virtualenv in $(VENV), then PyTorch ($(TORCH_SPEC)), then this project with its learn"
	@echo "and test extras (Warp, h5py, matplotlib, trimesh; Open3D, pyroomacoustics, onnxruntime, mcap for the tests)"
	python3 -m venv $(VENV)
	$(PY) -m pip install --progress-bar on "$(TORCH_SPEC)"
	$(PY) -m pip install --progress-bar on -e ".[learn,test]"
	touch $@

# Open3D (a test-only reference) needs libusb at import time.
system-deps:
	@if ! ldconfig -p | grep -q libusb-1.0.so.0; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else echo "note: install libusb-1.0-0 (e.g. sudo apt-get install libusb-1.0-0) for the Open3D test reference"; fi; \
	fi

demo: $(VENV)/.installed
	$(PY) -m acoustic_sim render --scene office --seed 0 --frames 150 --frame 60 --device $(DEVICE) --out $(OUT)/office.png --overwrite
	$(PY) -m acoustic_sim render --sonar --scene office --seed 0 --frames 40 --frame 30 --device $(DEVICE) --out $(OUT)/sonar_office.png --overwrite
	$(PY) -m acoustic_sim generate --suite paper --frames $(DEMO_FRAMES) --workers 2 --device $(DEVICE) --out $(OUT)/data
	$(PY) -m acoustic_sim generate --suite paper --frames $(DEMO_DRIVE_FRAMES) --seed 2026 --shards 2 --workers 2 --device $(DEVICE) --out $(OUT)/drive
	$(PY) -m learn train --data $(OUT)/data --out $(OUT)/run --model polar_unet $(DEMO_TRAIN) --device $(DEVICE)
	$(PY) -m learn evaluate --checkpoint pretrained=$(PRETRAINED) --checkpoint "smoke run=$(OUT)/run/best.pt" \
	  --checkpoint "k5 randomised=$(K5_RANDOMISED)" --checkpoint "memory=$(MEMORY)" \
	  --data $(OUT)/drive --out $(OUT)/report --device $(DEVICE) --overwrite
	@echo "beside the report: $(OUT)/report/examples.png (the pretrained model on the fresh drive), examples_memory.png"
	@echo "(the model with memory, trained on the randomised suite beside 'k5 randomised'), the smoke run's"
	@echo "curves $(OUT)/run/curves.png, the dataset card $(OUT)/data/README.md and the scene pictures $(OUT)/*.png"

test: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q --durations=15

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache

# Set-up and the two main commands. `make demo` runs the main job on a small CPU default;
# `make test` runs the test suite. Both create the virtualenv on first use.
VENV ?= .venv
PY := $(VENV)/bin/python
# CPU build of torch; on a GPU machine use e.g. TORCH_SPEC="torch" (CUDA build).
TORCH_SPEC ?= torch==2.13.0
OUT ?= out
DEVICE ?= cpu

.PHONY: demo test lint system-deps clean

$(VENV)/.installed: pyproject.toml
	@$(MAKE) --no-print-directory system-deps
	python3 -m venv $(VENV)
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[test]"
	touch $@

# Open3D (a test-only reference) needs libusb at import time.
system-deps:
	@if ! ldconfig -p | grep -q libusb-1.0.so.0; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else echo "note: install libusb-1.0-0 (e.g. sudo apt-get install libusb-1.0-0) for the Open3D test reference"; fi; \
	fi

demo: $(VENV)/.installed
	$(PY) -m acoustic_sim render --scene office --seed 0 --frames 150 --frame 60 --device $(DEVICE) --out $(OUT)/office.png
	$(PY) -m acoustic_sim render --scene corridor --seed 0 --frames 150 --frame 60 --device $(DEVICE) --out $(OUT)/corridor.png
	$(PY) -m acoustic_sim render --scene random_world --seed 0 --frames 150 --frame 60 --device $(DEVICE) --out $(OUT)/random_world.png
	$(PY) -m acoustic_sim generate --suite paper --frames 300 --workers 2 --device $(DEVICE) --out $(OUT)/data
	@echo "pictures in $(OUT)/, dataset and its card in $(OUT)/data/"

test: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache

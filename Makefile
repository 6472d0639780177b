# Two set-up commands (README): `make demo` and `make test`. Both create/update .venv idempotently.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
# CPU build of torch first: a plain `torch` requirement would pull several GB of CUDA wheels.
TORCH_PIN := torch==2.13.0

.PHONY: install demo test lint bench gallery clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q $(TORCH_PIN)
	$(PY) -m pip install -q -e ".[dev,text,lora,rl,video,nuscenes]"
	$(PY) -m pip install -q --no-deps nuscenes-devkit==1.2.0
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(VENV)/bin/m4world demo

test: install
	$(PY) -m pytest -q -n 2 --dist loadfile tests

lint: install
	$(VENV)/bin/ruff check world_model m4world_env tests benchmarks examples

bench: install
	$(VENV)/bin/m4world bench --out out/bench

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache

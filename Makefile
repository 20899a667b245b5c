# playseg — the two commands a new machine needs: `make demo` and `make test`.
# Both first run `setup` (idempotent: seconds when nothing changed).
VENV ?= .venv
PY := $(VENV)/bin/python
# The demo runs on its own ROS graph: domain 77 and localhost-only discovery, so it neither sees nor
# disturbs other ROS 2 processes (override: make demo ROS_DOMAIN_ID=5). Tests pick their own domain per run
# (tests/conftest.py).
DEMO_ENV := ROS_DOMAIN_ID=$(or $(ROS_DOMAIN_ID),77) ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST

.PHONY: setup demo test test-fast fuzz lint format bags models bench clean lerobot-check io-check

setup:
	@bash scripts/setup_env.sh

demo: setup
	$(DEMO_ENV) $(PY) -m playseg_ros.cli demo

test: setup
	$(PY) -m pytest -q tests

# The quick tier while working: no ROS 2 nodes or DDS, no training beyond seconds (markers `dds`, `slow`).
test-fast: setup
	$(PY) -m pytest -q -m "not dds and not slow" tests

# The fuzz tests (pytest -m fuzz) with many more examples each: minutes instead of seconds.
fuzz: setup
	HYPOTHESIS_PROFILE=fuzz $(PY) -m pytest -q -m fuzz tests

# The LeRobot export read by the real `lerobot` (LeRobotDataset, offline) and compared frame by frame
# with its source (docs/convert.md, LeRobot v3.0). lerobot needs Python 3.12 and torch < 2.12: its own
# environment, ~/.cache/playseg/lerobot-venv (scripts/setup_lerobot_env.sh; built once, ~2.5 min and ~5.4 GB).
LEROBOT_CHECK_DIR ?= build/lerobot-check
LEROBOT_VENV ?= $(or $(XDG_CACHE_HOME),$(HOME)/.cache)/playseg/lerobot-venv
lerobot-check: setup
	@LEROBOT_VENV=$(LEROBOT_VENV) bash scripts/setup_lerobot_env.sh
	$(PY) scripts/lerobot_export.py $(LEROBOT_CHECK_DIR)
	HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 $(LEROBOT_VENV)/bin/python scripts/lerobot_check.py \
		$(LEROBOT_CHECK_DIR)/tabletop $(LEROBOT_CHECK_DIR)/synthetic

# The ROS-free I/O part installed alone (requirements-io.txt: no ROS 2 wheels, playseg_msgs or torch) in
# its own environment, ~/.cache/playseg/io-venv (scripts/setup_io_env.sh), runs `playseg bag` and
# `playseg convert` on bags/tabletop (docs/setup.md "The I/O part alone"). Needs PyPI the first time.
IO_CHECK_DIR ?= build/io-check
IO_VENV ?= $(or $(XDG_CACHE_HOME),$(HOME)/.cache)/playseg/io-venv
io-check:
	@IO_VENV=$(IO_VENV) bash scripts/setup_io_env.sh
	$(IO_VENV)/bin/python scripts/io_check.py $(CURDIR) $(abspath $(IO_CHECK_DIR))

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

format: setup
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

# The sample bags in bags/ (see bags/README.md): the `sample` preset, seed 0, written as play bags and
# copied into bags/, and the tabletop robot bags in bags/tabletop. Deterministic: running it again gives
# byte-identical files.
bags: setup
	$(PY) -m playseg_ros.cli generate --preset sample --seed 0 --out build/sample --workers 2 --overwrite --quiet --bag
	rm -rf bags/annotated bags/play bags/test
	cp -r build/sample/bags/annotated build/sample/bags/play build/sample/bags/test bags/
	# tabletop play of CALVIN's 32 task types as a robot records it (standard messages, docs/tabletop.md): an
	# annotated bag of 6 tasks, unannotated ones of 4 and 30 (the demo replays the long one)
	$(PY) -m playseg_ros.tabletop.bags --out bags/tabletop --tasks 6 4 30 --annotated 1 --task-set calvin \
		--images jpeg --overwrite

# The sample PS models the demo uses (bags/models, bags/README.md): BabyAI's trained on bags/annotated,
# the tabletop's on generated play (playseg_ros/demo.py TABLETOP_RECIPE). Without them `make demo` trains
# stand-ins (slower, and the tabletop one far weaker).
models: setup
	$(PY) -m playseg_ros.cli demo --train-models

clean:
	rm -rf build $(VENV) .pytest_cache

# walkers: `make help` lists the targets. Every target bootstraps .venv on a fresh machine.
.DEFAULT_GOAL := help
SHELL := /bin/bash

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
MLFLOW_PORT ?= 5000
ARGS ?=
# make bench-learning: the study of walkers against its Stable-Baselines3 twins
BENCH_ALGOS ?= td3,sac
BENCH_ENV ?= walker2d
BENCH_STEPS ?= 100000
BENCH_SEEDS ?= 3
BENCH_EXPERIMENT ?= bench_learning_$(BENCH_ENV)
# make baseline: one algorithm's locomotion baseline, keyed so that the same command continues it
BASELINE_ALGO ?= td3
BASELINE_ENVS ?= walker2d,hopper,half_cheetah
BASELINE_SEEDS ?= 0,1,2
BASELINE_STEPS ?= 1000000
BASELINE_STORE ?= sqlite:///.walkers/baselines.db
# make study-original: a study of hours, kept outside the work tree so that a new checkout continues it
ORIGINAL_DIR ?= $(HOME)/.walkers/original
CORES := $(shell nproc)

help:  ## list the make targets
	@grep -hE '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*## "}; {printf "  make %-16s %s\n", $$1, $$2}'

# Quiet: errors only (pip's -qq also silences the build backend's notes on editable installs).
$(STAMP): pyproject.toml
	@$(PYTHON) -m venv $(VENV)
	@$(VENV)/bin/pip install -qq --upgrade pip
	@$(VENV)/bin/pip install -qq -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP)  ## create .venv and install walkers with pinned dependencies

train: $(STAMP)  ## the main job: TD3 on Walker2d-v5, 1M steps, logged to ./mlflow.db (extra overrides: ARGS="seed=3 ...")
	$(PY) -m walkers.train $(ARGS)

ab: $(STAMP)  ## a small A/B end to end in minutes: REINFORCE vs TD3 on Pendulum, 5 seeds each, then a report
	$(PY) -m walkers.train -m experiment=ab_pendulum hydra/launcher=joblib $(ARGS)
	$(PY) -m walkers.compare env=pendulum algos=[reinforce,td3] tracking.experiment=ab_pendulum

ab-all: $(STAMP)  ## the extended A/B in minutes: REINFORCE, PPO, DDPG, TD3, SAC x 5 seeds on InvertedPendulum, then a report
	$(PY) -m walkers.train -m experiment=ab_all_inverted_pendulum hydra/launcher=joblib $(ARGS)
	$(PY) -m walkers.compare env=inverted_pendulum algos=[reinforce,ppo,ddpg,td3,sac] tracking.experiment=ab_all_inverted_pendulum

offline: $(STAMP)  ## offline RL end to end in minutes: TD3 on Pendulum -> Minari dataset -> Decision Transformer -> report
	$(PY) -m walkers.train experiment=offline_pendulum_td3 $(ARGS)
	$(PY) -m walkers.collect run_id=latest env=pendulum tracking.experiment=offline_pendulum episodes=40 dataset=walkers/pendulum/td3-demo overwrite=true
	$(PY) -m walkers.train experiment=offline_pendulum_dt
	$(PY) -m walkers.compare env=pendulum algos=[td3,dt] tracking.experiment=offline_pendulum

study: $(STAMP)  ## an A/B study to its verdict in minutes: REINFORCE vs TD3 on Pendulum and InvertedPendulum, seeds in rounds (conf/ab/tiny.yaml); rerun to pick up where it stopped
	$(PY) -m walkers.train -m ab=tiny hydra/launcher=joblib $(ARGS)

baseline: $(STAMP)  ## one algorithm's locomotion baseline at its defaults: 1M steps x seeds 0-2 x Walker2d, Hopper, HalfCheetah, one torch thread, into .walkers/baselines.db; Ctrl-C stops it at a checkpoint and the same command continues it, across sessions (BASELINE_ALGO=td3 BASELINE_ENVS=hopper BASELINE_SEEDS=0; off-policy seeds as one population: BASELINE_SEEDS=0 ARGS=population=3); then `python -m walkers.export` it into results/
	$(PY) -m walkers.train -m algo=$(BASELINE_ALGO) 'env=$(BASELINE_ENVS)' 'seed=$(BASELINE_SEEDS)' total_steps=$(BASELINE_STEPS) torch_threads=1 progress=false 'job_key="baseline/$(BASELINE_ALGO)/$${env.id}/{seed}"' 'tracking.run_name="baseline-$(BASELINE_ALGO)-$${env.id}-s{seed}"' tracking.experiment=baseline_$(BASELINE_ALGO) tracking.uri=$(BASELINE_STORE) $(ARGS)

study-original: $(STAMP)  ## the original study at its full budget (TD3 vs REINFORCE, Walker2d-v5, 1M steps) in the background at the lowest priority, one job a core, one torch thread a job, its store, checkpoints and replay buffers in $$ORIGINAL_DIR (~/.walkers/original), REINFORCE's arm imported from results/reinforce_walker2d; the same command continues it
	@mkdir -p $(ORIGINAL_DIR)
	$(PY) -m walkers.ingest bundle=results/reinforce_walker2d/bundle tracking.uri=sqlite:///$(ORIGINAL_DIR)/mlflow.db
	WALKERS_WORK_DIR=$(ORIGINAL_DIR)/work nice -n 19 $(PY) -m walkers.train -m ab=original hydra/launcher=joblib hydra.launcher.n_jobs=$(CORES) torch_threads=1 tracking.uri=sqlite:///$(ORIGINAL_DIR)/mlflow.db 'hydra.sweep.dir=$(ORIGINAL_DIR)/multirun/$${now:%Y-%m-%d_%H-%M-%S}' $(ARGS)

compare: $(STAMP)  ## A/B report from finished runs (ARGS="env=walker2d algos=[reinforce,td3] tracking.experiment=...")
	$(PY) -m walkers.compare $(ARGS)

plan: $(STAMP)  ## how many seeds a study needs, from pilot runs (ARGS="env=pendulum algos=[reinforce,td3] tracking.experiment=ab_pendulum relative=0.1")
	$(PY) -m walkers.plan $(ARGS)

test: $(STAMP)  ## run the test suite (real tiny trainings, sweeps, offline RL, reports; one worker per core)
	$(PY) -m pytest -q -n auto --dist loadscope --durations=10 -m "not cluster and not browser and not faults and not slow" $(ARGS)

test-slow: $(STAMP)  ## the long end-to-end tests (marker `slow`): algorithms learning a task, SB3 twins trained and resumed, sweeps and runs resumed, the offline chain on a learned policy (CI runs it after `make test`)
	$(PY) -m pytest -q -n auto --dist loadscope --durations=10 -m slow $(ARGS)

test-faults: $(STAMP)  ## the fault tests: kill -9 of a run and of a study's driver, SIGTERM to a process group, a tracking server that dies mid-run, a resume that cannot reopen its run (a few minutes; CI runs it after `make test`)
	$(PY) -m pytest -q -n auto --dist loadscope --durations=5 -m faults $(ARGS)

# The newest Python the README names (3.13), in a venv of its own: a python3.13 on the PATH that
# runs (pyenv's shim does not unless 3.13 is selected), else pyenv's own.
NEWEST_PYTHON ?= $(firstword $(shell python3.13 -c 'import sys; print(sys.executable)' 2>/dev/null) $(wildcard $(HOME)/.pyenv/versions/3.13*/bin/python3.13))
NEWEST_VENV := .venv-newest

test-newest-python:  ## the foundation and training tests on Python 3.13, the newest the README names, in .venv-newest (CI runs it)
	@test -n "$(NEWEST_PYTHON)" || { echo "error: no python3.13 on the PATH or in ~/.pyenv/versions: install Python 3.13 (e.g. pyenv install 3.13), or pass NEWEST_PYTHON=<its path>" >&2; exit 2; }
	@test -f $(NEWEST_VENV)/.installed || { $(NEWEST_PYTHON) -m venv $(NEWEST_VENV) && $(NEWEST_VENV)/bin/pip install -qq --upgrade pip && $(NEWEST_VENV)/bin/pip install -qq -e '.[dev]' && touch $(NEWEST_VENV)/.installed; }
	$(NEWEST_VENV)/bin/python -m pytest -q -n auto --dist loadscope -m "not cluster and not browser and not faults and not slow" tests/test_config.py tests/test_bad_input.py tests/test_random_streams.py tests/data tests/training tests/agents/test_resume_every_algorithm.py $(ARGS)

ui-check: $(STAMP)  ## the links walkers prints open MLflow's training view, and the docs site renders, in a real headless Chromium (installs Debian's chromium if missing)
	@command -v chromium >/dev/null || (apt-get update -qq && apt-get install -y -qq chromium >/dev/null)
	$(PY) -m pytest -q -m browser $(ARGS)

test-cluster: $(STAMP)  ## the scale-out tests: a real Ray cluster on loopback, PostgreSQL, an MLflow server (minutes)
	$(PY) -m pytest -q -m cluster --durations=10 $(ARGS)

chaos: $(STAMP)  ## the fault matrix: a sweep on a loopback cluster under every fault, repeated; prints the table (ARGS="--reps 3 --seed 0")
	$(PY) -m tests.chaos $(ARGS)

stack: $(STAMP)  ## PostgreSQL + an MLflow server on it for a team or a cluster, until Ctrl-C (prints the URIs; MLFLOW_PORT=...)
	$(PY) -m walkers.stack --port $(MLFLOW_PORT) $(ARGS)

bench: $(STAMP)  ## benchmarks: the TD3 update vs a plain eager implementation, side by side
	$(PY) benchmarks/bench_update.py $(ARGS)

bench-population: $(STAMP)  ## what a population's lockstep step costs per member through walkers.train itself (TD3, Walker2d-v5, K = 1, 4, 16, warm-up phase), beside the bare env step, and where its host time goes (ARGS="--reps 3 --against ../main-before" pairs it with another checkout)
	$(PY) benchmarks/bench_population.py --split $(ARGS)

bench-throughput: $(STAMP)  ## env steps/s of walkers TD3/DDPG/SAC/CrossQ/PPO (1, 4, 8 envs)/REINFORCE vs Stable-Baselines3 (and sb3-contrib) on Walker2d
	$(PY) benchmarks/bench_throughput.py $(ARGS)

bench-gpu: $(STAMP)  ## the prepared script for a GPU machine, under 9 minutes: the TD3 update vs a plain one and by phase on CUDA, TD3/SAC/PPO throughput with populations of 1, 5 and 16, a TD3 population through walkers.train itself (bench_population), DT's step (each part under its own timeout)
	timeout 90 $(PY) benchmarks/bench_update.py --device cuda --reps 3 --phases
	timeout 180 $(PY) benchmarks/bench_throughput.py --device cuda --only "TD3,SAC,PPO" --population 1,5,16 --reps 2 --steps 200
	timeout 240 $(PY) benchmarks/bench_population.py --device cuda --phase learning --populations 1,5,16 --reps 1 --steps 3000 --log-every 500 --split
	timeout 30 $(PY) benchmarks/bench_dt.py --devices cuda --reps 2 --steps 10

offline-gpu:  ## on a GPU machine: the offline study's arms, DT and TD3+BC seeds 0-2, on one dataset carried in .walkers/datasets (DATASET=walkers/walker2d/medium-v0), side by side, each algorithm's finished runs a bundle in $$OUT/bundles for walkers.ingest here (benchmarks/device_offline.sh; sets itself up from .whl/)
	bash benchmarks/device_offline.sh

baselines-gpu:  ## on a GPU machine: the next off-policy 100k baselines results/ lacks, 3 seeds as one captured population each, JOBS (1) at a time, each finished one a results page in $$OUT/results.tar.gz (benchmarks/device_baselines.sh; sets itself up from .whl/)
	bash benchmarks/device_baselines.sh

test-gpu: $(STAMP)  ## on a GPU machine: the agents, populations, PPO, checkpoints and resume with device=auto on CUDA (a CPU machine runs them on the CPU)
	$(PY) -m pytest -q -n 4 --dist loadscope -m "not cluster and not browser and not faults and not slow" tests/agents/test_algorithms.py tests/agents/test_population.py tests/agents/test_ppo.py tests/agents/test_ppo_vector.py tests/training/test_checkpoints.py tests/training/test_seeds_and_resume.py tests/agents/test_health.py tests/agents/test_td3.py tests/agents/test_sac.py tests/agents/test_capture.py tests/test_random_streams.py $(ARGS)

bench-envs: $(STAMP)  ## how N training envs step on this machine's cores: a sequential loop, Gymnasium's SyncVectorEnv and AsyncVectorEnv, and envpool when installed (ARGS="--envs 1,2,4,8")
	$(PY) benchmarks/bench_envs.py $(ARGS)

bench-time-to-walk: $(STAMP)  ## PPO's wall time to its first evaluation >= 3,000 on Walker2d through walkers.train, algo.num_envs=1 beside 8, 3 seeds (half an hour or more on 2 cores; ARGS="--envs 1,8 --seeds 0,1,2 --budget 500000")
	$(PY) benchmarks/bench_time_to_walk.py $(ARGS)

bench-dt: $(STAMP)  ## the Decision Transformer's gradient step at its reference size, per device (ARGS="--devices cpu,cuda")
	$(PY) benchmarks/bench_dt.py $(ARGS)

bench-learning: $(STAMP)  ## walkers vs its Stable-Baselines3 twins through the platform: impl=walkers,sb3 x seeds, then a group_by=impl report (BENCH_ALGOS=td3,sac BENCH_ENV=walker2d BENCH_STEPS=100000 BENCH_SEEDS=3; quick: BENCH_ENV=pendulum BENCH_STEPS=15000)
	$(PY) -m walkers.train -m algo=$(BENCH_ALGOS) impl=walkers,sb3 env=$(BENCH_ENV) 'seed=range($(BENCH_SEEDS))' total_steps=$(BENCH_STEPS) torch_threads=1 progress=false tracking.experiment=$(BENCH_EXPERIMENT) hydra/launcher=joblib hydra.launcher.n_jobs=2 $(ARGS)
	$(PY) -m walkers.compare env=$(BENCH_ENV) algos=[$(BENCH_ALGOS)] group_by=impl total_steps=$(BENCH_STEPS) tracking.experiment=$(BENCH_EXPERIMENT)

bench-sequential: $(STAMP)  ## the A/B study's stopping rule by simulation: family-wise error, power and seeds saved against a fixed-n design (ARGS="--studies 1000")
	$(PY) benchmarks/bench_sequential.py $(ARGS)

bench-scale: $(STAMP)  ## a seed study through joblib vs a loopback Ray cluster of 1 and 2 workers; the study and a sweep with N workers on paper
	$(PY) benchmarks/bench_scale.py $(ARGS)

docs: $(STAMP)  ## the documentation site (MkDocs, Material) with --strict into site/: a broken link or a missing page fails; its results pages from results/, its home page from README.md
	$(PY) -m walkers.results --docs docs >/dev/null
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict -q

results: $(STAMP)  ## write every results/<page>/report anew from its bundle (ARGS="tiny" for one page)
	$(PY) -m walkers.results $(ARGS)

menus: $(STAMP)  ## rewrite conf/algo/*.yaml from the hyperparameters declared in walkers/agents/declarations/schemas.py, and conf/train.yaml's run settings from walkers/training/settings.py
	$(PY) -m walkers.agents.declarations.menus
	$(PY) -m walkers.training.settings

lint: $(STAMP)  ## ruff (style, common bugs) and lint-imports (imports point down the layers)
	$(VENV)/bin/ruff check walkers tests $(wildcard benchmarks)
	$(VENV)/bin/lint-imports

ui: $(STAMP)  ## MLflow UI on the local store: http://127.0.0.1:5000 (MLFLOW_PORT=... to change)
	@echo "the training runs: http://127.0.0.1:$(MLFLOW_PORT)/#/experiments/<experiment id>/runs?workflowType=machine_learning (every run prints its own link)"
	$(VENV)/bin/mlflow ui --backend-store-uri sqlite:///mlflow.db --port $(MLFLOW_PORT)

dashboard: $(STAMP)  ## optuna-dashboard on the sweeps' study storage: ./optuna.db, or ARGS=optuna=postgres ($$WALKERS_OPTUNA_STORAGE); http://127.0.0.1:8080
	$(PY) -m walkers.dashboard $(ARGS)

clean:  ## remove run outputs (mlflow.db, mlartifacts/, outputs/, multirun/, .walkers/, reports/) and caches; keeps .venv and optuna.db
	rm -rf mlflow.db mlruns mlartifacts outputs multirun .walkers reports .pytest_cache .ruff_cache
	find . -name __pycache__ -type d -prune -not -path './$(VENV)/*' -exec rm -rf {} +

.PHONY: help install train ab ab-all study baseline baselines-gpu offline-gpu offline compare plan results docs dashboard bench-sequential ui-check test test-slow test-faults test-cluster chaos stack bench bench-population bench-throughput bench-dt bench-learning bench-scale menus lint ui clean

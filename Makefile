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
# make study-original, study-bipedal: studies of hours, each in STUDIES_DIR/<study> (its store,
# checkpoints and replay buffers), outside the work tree so that a new checkout continues them
STUDIES_DIR ?= $(HOME)/.walkers
CORES := $(shell nproc)

help:  ## list the make targets and the Makefile's options
	@grep -hE '^[a-zA-Z0-9_-]+:.*## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*## "}; \
		{line = sprintf("  make %-18s %s", $$1, $$2); \
		print (length(line) > 100 ? substr(line, 1, 97) "..." : line)}'
	@printf '%s\n' '' \
		'Options, as make TARGET VAR=value: ARGS="..." adds arguments (make train ARGS="seed=3"),' \
		'PYTHON is the Python of a new .venv (make install PYTHON=python3.12), TORCH_INDEX where its' \
		'torch comes from (CPU build: https://download.pytorch.org/whl/cpu), MLFLOW_PORT (ui, stack),' \
		"BENCH_*, BASELINE_*, STUDIES_DIR, NEWEST_PYTHON (their targets'): docs/make-targets.md"

# Quiet but for a line before and after: pip's -qq also silences the build backend's notes on
# editable installs. TORCH_INDEX: where torch comes from first (PyTorch's own index for the CPU
# build, docs/dependencies.md); empty: the registry's, which on Linux is the CUDA build.
TORCH_PIN := $(shell grep -o '"torch==[^"]*"' pyproject.toml | tr -d '"')
TORCH_INDEX ?=
$(STAMP): pyproject.toml
	@$(PYTHON) -m venv $(VENV)
	@$(VENV)/bin/pip install -qq --upgrade pip
	@echo "installing walkers into $(VENV) with $(TORCH_PIN) $(if $(TORCH_INDEX),from $(TORCH_INDEX),from the registry (on Linux its CUDA build, about 3.4 GB, unless a local wheel is found; CPU only: TORCH_INDEX=https://download.pytorch.org/whl/cpu)): a few minutes"
	@$(if $(TORCH_INDEX),$(VENV)/bin/pip install -qq $(TORCH_PIN) --index-url $(TORCH_INDEX),true)
	@$(VENV)/bin/pip install -qq -e '.[dev]'
	@$(VENV)/bin/python -c "import torch; print(f'installed torch {torch.__version__}:', f'CUDA {torch.version.cuda} build' if torch.version.cuda else 'CPU build')"
	@touch $(STAMP)

install: $(STAMP)  ## create .venv and install walkers with pinned dependencies

# A Ctrl-C ends a training target quietly: walkers' "interrupted: ..." line, which says how the
# same command continues, is the last (its exit status 130 is not made an error). Any other
# failure stays one, with its own status.
CTRL_C_QUIET = || { rc=$$?; [ $$rc = 130 ] || exit $$rc; }

train: $(STAMP)  ## the main job: TD3 on Walker2d-v5, 1M steps, logged to ./mlflow.db
	$(PY) -m walkers.train $(ARGS) $(CTRL_C_QUIET)

ab: $(STAMP)  ## a small A/B in minutes: REINFORCE vs TD3 on Pendulum, 5 seeds, a report
	$(PY) -m walkers.train -m experiment=ab_pendulum hydra/launcher=joblib $(ARGS) \
		&& $(PY) -m walkers.compare env=pendulum algos=[reinforce,td3] tracking.experiment=ab_pendulum $(CTRL_C_QUIET)

ab-all: $(STAMP)  ## the extended A/B: 5 algorithms x 5 seeds on InvertedPendulum, a report
	$(PY) -m walkers.train -m experiment=ab_all_inverted_pendulum hydra/launcher=joblib $(ARGS) \
		&& $(PY) -m walkers.compare env=inverted_pendulum algos=[reinforce,ppo,ddpg,td3,sac] tracking.experiment=ab_all_inverted_pendulum $(CTRL_C_QUIET)

offline: $(STAMP)  ## offline RL in minutes: TD3 -> Minari dataset -> Decision Transformer
	$(PY) -m walkers.train experiment=offline_pendulum_td3 $(ARGS)
	$(PY) -m walkers.collect run_id=latest env=pendulum tracking.experiment=offline_pendulum episodes=40 dataset=walkers/pendulum/td3-demo overwrite=true
	$(PY) -m walkers.train experiment=offline_pendulum_dt
	$(PY) -m walkers.compare env=pendulum algos=[td3,dt] tracking.experiment=offline_pendulum

study: $(STAMP)  ## an A/B study in rounds to its verdict in minutes; rerun to continue
	$(PY) -m walkers.train -m ab=tiny $(ARGS) $(CTRL_C_QUIET)

baseline: $(STAMP)  ## one algorithm's 1M-step baseline (3 envs x 3 seeds); rerun to continue
	$(PY) -m walkers.train -m algo=$(BASELINE_ALGO) 'env=$(BASELINE_ENVS)' 'seed=$(BASELINE_SEEDS)' total_steps=$(BASELINE_STEPS) hydra/launcher=joblib progress=false 'job_key="baseline/$(BASELINE_ALGO)/$${env.id}/{seed}"' 'tracking.run_name="baseline-$(BASELINE_ALGO)-$${env.id}-s{seed}"' tracking.experiment=baseline_$(BASELINE_ALGO) tracking.uri=$(BASELINE_STORE) $(ARGS) $(CTRL_C_QUIET)

# A study at its full budget on this machine, in the background at the lowest priority (one job
# a core, one torch thread a job), its store and work in STUDIES_DIR/<study>: a recipe's line
# $(call background_study,NAME). First the study's committed bundles, where they exist:
# results/NAME_in_flight (its seeds in flight when a session ended, with their checkpoints: a new
# machine continues them) and results/NAME (the study ended: the command answers at once); on the
# machine that trained them they add nothing. The same command continues the study.
define background_study
@mkdir -p $(STUDIES_DIR)/$(1)
@for bundle in results/$(1)_in_flight/bundle results/$(1)/bundle; do if [ -d $$bundle ]; then \
	$(PY) -m walkers.ingest bundle=$$bundle tracking.uri=sqlite:///$(STUDIES_DIR)/$(1)/mlflow.db || exit; fi; done
WALKERS_WORK_DIR=$(STUDIES_DIR)/$(1)/work nice -n 19 $(PY) -m walkers.train -m ab=$(1) \
	hydra.launcher.n_jobs=$(CORES) torch_threads=1 tracking.uri=sqlite:///$(STUDIES_DIR)/$(1)/mlflow.db \
	'hydra.sweep.dir=$(STUDIES_DIR)/$(1)/multirun/$${now:%Y-%m-%d_%H-%M-%S}' $(ARGS) $(CTRL_C_QUIET)
endef

study-original: $(STAMP)  ## the original study at 1M steps, at nice 19, in ~/.walkers/original
	@mkdir -p $(STUDIES_DIR)/original
	@# its REINFORCE arm, trained first under the study's job keys
	$(PY) -m walkers.ingest bundle=results/reinforce_walker2d/bundle tracking.uri=sqlite:///$(STUDIES_DIR)/original/mlflow.db
	$(call background_study,original)

study-bipedal: $(STAMP)  ## the tutorial's study, TD3 vs DDPG on BipedalWalker-v3, at nice 19
	$(call background_study,bipedal)

study-td3-compile: $(STAMP)  ## TD3 eager vs its CPU-compiled update on Walker2d (equal?), nice 19
	$(call background_study,td3_compile)

study-td3-bf16: $(STAMP)  ## TD3 eager vs compiled in bfloat16 on Walker2d (equal?), nice 19
	$(call background_study,td3_bf16)

compare: $(STAMP)  ## an A/B report from finished runs (ARGS="env=... algos=[...] ...")
	$(PY) -m walkers.compare $(ARGS)

plan: $(STAMP)  ## how many seeds a study needs, from pilot runs
	$(PY) -m walkers.plan $(ARGS)

# The default suite: everything but the long, fault, cluster and browser tests (their own targets).
DEFAULT_SUITE := -n auto --dist loadscope -m "not cluster and not browser and not faults and not slow"
test: $(STAMP)  ## the test suite: real tiny trainings, sweeps, offline RL, reports
	$(PY) -m pytest -q --durations=10 $(DEFAULT_SUITE) $(ARGS)

test-slow: $(STAMP)  ## the long end-to-end tests (marker slow; CI runs them)
	$(PY) -m pytest -q -n auto --dist loadscope --durations=10 -m slow $(ARGS)

test-faults: $(STAMP)  ## the fault tests: kill -9, SIGTERM, a tracking server that dies
	$(PY) -m pytest -q -n auto --dist loadscope --durations=5 -m faults $(ARGS)

# The newest Python the README names (3.13), in a venv of its own: a python3.13 on the PATH that
# runs (pyenv's shim does not unless 3.13 is selected), else pyenv's own.
NEWEST_PYTHON ?= $(firstword $(shell python3.13 -c 'import sys; print(sys.executable)' 2>/dev/null) $(wildcard $(HOME)/.pyenv/versions/3.13*/bin/python3.13))
NEWEST_VENV := .venv-newest

test-newest-python: newest-venv  ## make test's suite on Python 3.13, in .venv-newest (CI runs it)
	$(NEWEST_VENV)/bin/python -m pytest -q $(DEFAULT_SUITE) $(ARGS)

newest-venv:  ## create .venv-newest with Python 3.13 (CI installs it beside make test)
	@test -n "$(NEWEST_PYTHON)" || { echo "error: no python3.13 on the PATH or in ~/.pyenv/versions: install Python 3.13 (e.g. pyenv install 3.13), or pass NEWEST_PYTHON=<its path>" >&2; exit 2; }
	@test -f $(NEWEST_VENV)/.installed || { $(NEWEST_PYTHON) -m venv $(NEWEST_VENV) && $(NEWEST_VENV)/bin/pip install -qq --upgrade pip && $(NEWEST_VENV)/bin/pip install -qq -e '.[dev]' && touch $(NEWEST_VENV)/.installed; }

ui-check: $(STAMP)  ## MLflow links and the docs site in a real headless Chromium
	@command -v chromium >/dev/null || (apt-get update -qq && apt-get install -y -qq chromium >/dev/null)
	$(PY) -m pytest -q -m browser $(ARGS)

test-cluster: $(STAMP)  ## scale-out tests: Ray cluster on loopback, PostgreSQL, MLflow server
	$(PY) -m pytest -q -m cluster --durations=10 $(ARGS)

chaos: $(STAMP)  ## the fault matrix: a sweep on a loopback cluster under every fault
	$(PY) -m tests.chaos $(ARGS)

stack: $(STAMP)  ## PostgreSQL + an MLflow server on it, until Ctrl-C
	$(PY) -m walkers.stack --port $(MLFLOW_PORT) $(ARGS)

bench: $(STAMP)  ## the TD3 update vs a plain eager implementation
	$(PY) benchmarks/bench_update.py $(ARGS)

bench-profile: $(STAMP)  ## where a TD3 learning step of walkers.train goes on one CPU thread
	$(PY) benchmarks/profile_step.py $(ARGS)

bench-path: $(STAMP)  ## the files and classes of walkers/ that one walkers.train passes through
	$(PY) benchmarks/train_path.py $(ARGS)

bench-population: $(STAMP)  ## a population's lockstep step per member, K = 1, 4, 16
	$(PY) benchmarks/bench_population.py --split $(ARGS)

bench-threads: $(STAMP)  ## walkers.train's rate per torch thread setting, idle and 1 core busy
	$(PY) benchmarks/bench_threads.py $(ARGS)

bench-throughput: $(STAMP)  ## env steps/s of walkers vs SB3 and SBX: whole machine, then 1 core
	@$(PY) -c "import sbx" 2>/dev/null || { echo "installing the benchmark extras (SBX, JAX): pip install -e '.[bench]'"; $(PY) -m pip install -qq -e '.[bench]'; }
	$(PY) benchmarks/bench_throughput.py $(ARGS)
	taskset -c 0 $(PY) benchmarks/bench_throughput.py --only TD3,SAC,CrossQ $(ARGS)

bench-gpu: $(STAMP)  ## on a GPU machine: the prepared benchmarks, under 9 minutes
	timeout 90 $(PY) benchmarks/bench_update.py --device cuda --reps 3 --phases
	timeout 180 $(PY) benchmarks/bench_throughput.py --device cuda --only "TD3,SAC,PPO" --population 1,5,16 --reps 2 --steps 200
	timeout 240 $(PY) benchmarks/bench_population.py --device cuda --phase learning --populations 1,5,16 --reps 1 --steps 3000 --log-every 500 --split
	timeout 30 $(PY) benchmarks/bench_dt.py --devices cuda --reps 2 --steps 10

offline-gpu:  ## on a GPU machine: the offline study's DT and TD3+BC seeds, as bundles
	bash benchmarks/device_offline.sh

baselines-gpu:  ## on a GPU machine: the next off-policy 100k baselines, as results pages
	bash benchmarks/device_baselines.sh

test-gpu: $(STAMP)  ## on a GPU machine: the agents' and resume tests on CUDA
	$(PY) -m pytest -q -n 4 --dist loadscope -m "not cluster and not browser and not faults and not slow" tests/agents/test_algorithms.py tests/agents/test_population.py tests/agents/test_ppo.py tests/agents/test_ppo_vector.py tests/training/test_checkpoints.py tests/training/test_seeds_and_resume.py tests/agents/test_health.py tests/agents/test_td3.py tests/agents/test_sac.py tests/agents/test_capture.py tests/test_seeding.py $(ARGS)

bench-envs: $(STAMP)  ## how N training envs step on this machine: sequential, sync, async
	$(PY) benchmarks/bench_envs.py $(ARGS)

bench-time-to-walk: $(STAMP)  ## PPO's wall time to walk on Walker2d, 1 env beside 8
	$(PY) benchmarks/bench_time_to_walk.py $(ARGS)

bench-dt: $(STAMP)  ## the Decision Transformer's gradient step, per device
	$(PY) benchmarks/bench_dt.py $(ARGS)

bench-learning: $(STAMP)  ## walkers vs its Stable-Baselines3 twins, trained through the platform
	$(PY) -m walkers.train -m algo=$(BENCH_ALGOS) impl=walkers,sb3 env=$(BENCH_ENV) 'seed=range($(BENCH_SEEDS))' total_steps=$(BENCH_STEPS) torch_threads=1 progress=false tracking.experiment=$(BENCH_EXPERIMENT) hydra/launcher=joblib hydra.launcher.n_jobs=2 $(ARGS)
	$(PY) -m walkers.compare env=$(BENCH_ENV) algos=[$(BENCH_ALGOS)] group_by=impl total_steps=$(BENCH_STEPS) tracking.experiment=$(BENCH_EXPERIMENT)

bench-sequential: $(STAMP)  ## the A/B stopping rule by simulation: error, power, seeds saved
	$(PY) benchmarks/bench_sequential.py $(ARGS)

bench-scale: $(STAMP)  ## a seed study through joblib vs a loopback Ray cluster
	$(PY) benchmarks/bench_scale.py $(ARGS)

docs: $(STAMP)  ## the documentation site into site/ (MkDocs --strict)
	$(PY) -m walkers.results --docs docs >/dev/null
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict -q

results: $(STAMP)  ## write every results/<page>/report anew from its bundle
	$(PY) -m walkers.results $(ARGS)

menus: $(STAMP)  ## rewrite conf/algo/*.yaml, conf/train.yaml and --help from declarations
	$(PY) -m walkers.agents.declarations.menus
	$(PY) -m walkers.training.settings

lint: $(STAMP)  ## ruff and lint-imports (imports point down the layers)
	$(VENV)/bin/ruff check walkers tests $(wildcard benchmarks)
	$(VENV)/bin/lint-imports

ui: $(STAMP)  ## the MLflow UI on ./mlflow.db at http://127.0.0.1:5000
	@echo "the training runs: http://127.0.0.1:$(MLFLOW_PORT)/#/experiments/<experiment id>/runs?workflowType=machine_learning (every run prints its own link)"
	$(VENV)/bin/mlflow ui --backend-store-uri sqlite:///mlflow.db --port $(MLFLOW_PORT)

dashboard: $(STAMP)  ## optuna-dashboard on the sweeps' studies at http://127.0.0.1:8080
	$(PY) -m walkers.dashboard $(ARGS)

clean:  ## remove run outputs and caches; keeps .venv and optuna.db
	rm -rf mlflow.db mlruns mlartifacts outputs multirun .walkers reports .pytest_cache .ruff_cache
	find . -name __pycache__ -type d -prune -not -path './$(VENV)/*' -exec rm -rf {} +

.PHONY: help install train ab ab-all study study-original study-bipedal study-td3-compile study-td3-bf16 baseline baselines-gpu offline-gpu offline compare plan results docs dashboard bench-sequential ui-check test test-slow test-faults test-cluster chaos stack bench bench-profile bench-path bench-population bench-throughput bench-dt bench-learning bench-scale menus lint ui clean

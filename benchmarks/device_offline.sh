#!/usr/bin/env bash
# The offline call of a lent GPU: the offline study's arms on one dataset made here, the Decision
# Transformer's seeds (about 2.2 CPU-hours each at the reference size on one of this project's
# cores, minutes on an H200) and TD3+BC's beside them, their finished runs brought home as one
# bundle per algorithm for the study's store:
#
#   here:   bash benchmarks/device_wheels.sh                      # once: the wheels, in .whl/
#           the dataset under .walkers/datasets/ (MINARI_DATASETS_PATH=.walkers/datasets walkers.collect ...)
#   device: run(command="bash benchmarks/device_offline.sh", carry=[".whl", ".walkers/datasets"], timeout_s=560)
#   here:   python -m walkers.ingest bundle=<files_at>/bundles/<name> tracking.uri=<the study's store>
#
# Both arms learn from the one dataset carried here, so they are comparable whatever CPU made it
# (a rebuild elsewhere is other data: docs/offline.md, *One name, one build*). Each algorithm's
# seeds train side by side on the one GPU as the keyed multirun of docs/offline.md, each job
# keyed by algorithm, dataset and seed, so the ingested runs count as done there and the same
# command here skips them. Every job stops itself (SIGINT) DEADLINE seconds after the start; only
# FINISHED runs travel (walkers.export's default), so a stopped seed is trained again, not half-kept.
# Settings, by environment variable: DATASET (a Minari id), ENV, ARMS ("algo:gradient steps ...",
# the study's budgets: "dt:20000 td3bc:100000"), SEEDS (a Hydra sweep: 0,1,2), EVERY (gradient
# steps between evaluations and checkpoints), EXPERIMENT, DEADLINE (s), DEVICE (cuda; cpu tries
# the script here), EXTRA_DT, EXTRA_TD3BC (more overrides per algorithm, e.g. a small model for
# such a try), SETUP (0 skips device_venv.sh).
set -uo pipefail
export PYTHONUNBUFFERED=1 MUJOCO_GL=${MUJOCO_GL:-disable}
REPO=$PWD
OUT=${OUT:-/tmp/device_offline}
export MINARI_DATASETS_PATH=${MINARI_DATASETS_PATH:-$REPO/.walkers/datasets}
DATASET=${DATASET:-walkers/walker2d/medium-v0}
ENV=${ENV:-walker2d}
ARMS=${ARMS:-"dt:20000 td3bc:100000"}
SEEDS=${SEEDS:-0,1,2}
EVERY=${EVERY:-5000}
EXPERIMENT=${EXPERIMENT:-offline_walker2d}
DEADLINE=${DEADLINE:-440}
DEVICE=${DEVICE:-cuda}
algos=()
for arm in $ARMS; do
  algo=${arm%%:*}
  if [[ " ${algos[*]} " == *" $algo "* ]]; then
    echo "error: ARMS=\"$ARMS\" is not allowed: $algo is named twice" >&2
    exit 2
  fi
  algos+=("$algo")
done
WORK=$(mktemp -d)  # the store, checkpoints and Hydra's folders: only the bundle travels
trap 'rm -rf "$WORK"' EXIT  # however the call ends
mkdir -p "$OUT/bundles"
if [[ ${SETUP:-1} == 1 ]]; then
  bash benchmarks/device_venv.sh > "$OUT/setup.log" 2>&1 || { tail -20 "$OUT/setup.log"; exit 1; }
fi
py=$REPO/.venv/bin/python
slug=$(echo "${DATASET%-v*}" | tr '/' '_')
store="sqlite:///$WORK/offline.db"
jobs=$(echo "$SEEDS" | tr ',' '\n' | wc -l)
echo "device_offline: $ARMS on $DATASET, seeds $SEEDS, $DEVICE, until ${DEADLINE}s"
# the store first, once: the arms' multiruns would each migrate a new one at the same time
(cd "$WORK" && PYTHONPATH=$REPO "$py" -c "from walkers.tracking.client import connect; connect('$store')")

train() {  # train ALGO STEPS: the algorithm's seeds as the study's keyed multirun, to the deadline
  local algo=$1 steps=$2 extra_var="EXTRA_${1^^}"
  # shellcheck disable=SC2086  # EXTRA_<ALGO> is a list of overrides
  (cd "$WORK" && PYTHONPATH=$REPO timeout -s INT -k 45 "$DEADLINE" "$py" -m walkers.train -m \
    algo="$algo" env="$ENV" dataset="$DATASET" "seed=$SEEDS" total_steps="$steps" \
    eval_every="$EVERY" checkpoint_every="$EVERY" device="$DEVICE" torch_threads=2 progress=false \
    "job_key=offline/$algo/\${dataset}/\${seed}" tracking.experiment="$EXPERIMENT" \
    tracking.uri="$store" work_dir="$WORK/work" hydra.sweep.dir="$WORK/multirun/$algo" \
    hydra/launcher=joblib hydra.launcher.n_jobs="$jobs" ${!extra_var:-}) > "$OUT/${algo}_$slug.log" 2>&1
  local rc=$?
  echo "$rc $SECONDS" > "$WORK/$algo.ended"  # its own exit and time, whatever the other arms do
  return $rc
}

bring_home() {  # bring_home ALGO: its finished runs as $OUT/bundles/<algo>_<dataset>
  local algo=$1 name=${1}_$slug rc seconds
  read -r rc seconds < "$WORK/$algo.ended"
  case $rc in
    0) echo "$name: trained in ${seconds}s" ;;
    124) echo "$name: stopped at the deadline, ${DEADLINE}s (its unfinished runs stay on the machine)" ;;
    *) echo "$name: train exit $rc after ${seconds}s (its log: $OUT/$name.log)" ;;
  esac
  if (cd "$WORK" && PYTHONPATH=$REPO "$py" -m walkers.export tracking.uri="$store" \
      tracking.experiment="$EXPERIMENT" "where={algo: $algo}" out="$OUT/bundles/$name") \
      >> "$OUT/$name.log" 2>&1; then
    echo "$name: bundle in $OUT/bundles/$name"
  else
    echo "$name: nothing finished"
  fi
}

for arm in $ARMS; do
  train "${arm%%:*}" "${arm#*:}" &
done
wait  # every arm's multirun, each to its end or the deadline
: > "$OUT/summary.txt"
for algo in "${algos[@]}"; do
  bring_home "$algo" | tee -a "$OUT/summary.txt"
done
for arm in $ARMS; do
  grep -E "final/return|ended|error" "$OUT/${arm%%:*}_$slug.log" | tail -8
done

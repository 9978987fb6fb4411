#!/usr/bin/env bash
# The offline call of a lent GPU: Decision Transformer seeds (about 2.2 CPU-hours each at the
# reference size on one of this project's cores, minutes on an H200) on a dataset made here, their
# finished runs brought home as a bundle for the study's store:
#
#   here:   bash benchmarks/device_wheels.sh                      # once: the wheels, in .whl/
#           the dataset under .walkers/datasets/ (MINARI_DATASETS_PATH=.walkers/datasets walkers.collect ...)
#   device: run(command="bash benchmarks/device_offline.sh", carry=[".whl", ".walkers/datasets"], timeout_s=560)
#   here:   python -m walkers.ingest bundle=<files_at>/bundles/<name> tracking.uri=<the study's store>
#
# The seeds train side by side on the one GPU as the keyed multirun of docs/offline.md, each job
# keyed by algorithm, dataset and seed, so the ingested runs count as done there and the same
# command here skips them. Every job stops itself (SIGINT) DEADLINE seconds after the start; only
# FINISHED runs travel (walkers.export's default), so a stopped seed is trained again, not half-kept.
# Settings, by environment variable: DATASET (a Minari id), ENV, ALGO (dt; td3bc works the same),
# SEEDS (a Hydra sweep: 0,1,2), STEPS (gradient steps), EVERY (gradient steps between evaluations
# and checkpoints), EXPERIMENT, DEADLINE (s), DEVICE (cuda; cpu tries the script here), EXTRA
# (more overrides, e.g. a small model for such a try), SETUP (0 skips device_venv.sh).
set -uo pipefail
export PYTHONUNBUFFERED=1 MUJOCO_GL=${MUJOCO_GL:-disable}
REPO=$PWD
OUT=${OUT:-/tmp/device_offline}
export MINARI_DATASETS_PATH=${MINARI_DATASETS_PATH:-$REPO/.walkers/datasets}
DATASET=${DATASET:-walkers/walker2d/medium-v0}
ENV=${ENV:-walker2d}
ALGO=${ALGO:-dt}
SEEDS=${SEEDS:-0,1,2}
STEPS=${STEPS:-20000}
EVERY=${EVERY:-5000}
EXPERIMENT=${EXPERIMENT:-offline_walker2d}
DEADLINE=${DEADLINE:-440}
DEVICE=${DEVICE:-cuda}
EXTRA=${EXTRA:-}
WORK=$(mktemp -d)  # the store, checkpoints and Hydra's folders: only the bundle travels
trap 'rm -rf "$WORK"' EXIT  # however the call ends
mkdir -p "$OUT/bundles"
if [[ ${SETUP:-1} == 1 ]]; then
  bash benchmarks/device_venv.sh > "$OUT/setup.log" 2>&1 || { tail -20 "$OUT/setup.log"; exit 1; }
fi
py=$REPO/.venv/bin/python
name=${ALGO}_$(echo "${DATASET%-v*}" | tr '/' '_')
store="sqlite:///$WORK/offline.db"
jobs=$(echo "$SEEDS" | tr ',' '\n' | wc -l)
echo "device_offline: $ALGO on $DATASET, seeds $SEEDS, $STEPS gradient steps, $DEVICE, until ${DEADLINE}s"

# shellcheck disable=SC2086  # EXTRA is a list of overrides
(cd "$WORK" && PYTHONPATH=$REPO timeout -s INT -k 45 "$DEADLINE" "$py" -m walkers.train -m algo="$ALGO" \
  env="$ENV" dataset="$DATASET" "seed=$SEEDS" total_steps="$STEPS" eval_every="$EVERY" \
  checkpoint_every="$EVERY" device="$DEVICE" torch_threads=2 progress=false \
  "job_key=offline/$ALGO/\${dataset}/\${seed}" tracking.experiment="$EXPERIMENT" tracking.uri="$store" \
  work_dir="$WORK/work" hydra/launcher=joblib hydra.launcher.n_jobs="$jobs" $EXTRA) > "$OUT/$name.log" 2>&1
rc=$?
{
  case $rc in
    0) echo "$name: trained in ${SECONDS}s" ;;
    124) echo "$name: stopped at the deadline, ${DEADLINE}s (its unfinished runs stay on the machine)" ;;
    *) echo "$name: train exit $rc after ${SECONDS}s (its log: $OUT/$name.log)" ;;
  esac
  if (cd "$WORK" && PYTHONPATH=$REPO "$py" -m walkers.export tracking.uri="$store" \
      tracking.experiment="$EXPERIMENT" out="$OUT/bundles/$name") >> "$OUT/$name.log" 2>&1; then
    echo "$name: bundle in $OUT/bundles/$name"
  else
    echo "$name: nothing finished"
  fi
} | tee "$OUT/summary.txt"
grep -E "final/return|ended|error" "$OUT/$name.log" | tail -8

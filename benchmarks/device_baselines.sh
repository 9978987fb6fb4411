#!/usr/bin/env bash
# The results call of a lent GPU: off-policy locomotion baselines that results/ lacks, at 100k env
# steps, each (algorithm, env)'s 3 seeds as one captured population, JOBS of them side by side on
# the one GPU, each one that finishes exported as a results page (bundle + page.yaml), the pages
# brought home as one $OUT/results.tar.gz and the logs as $OUT/logs.tar.gz (a call brings back at
# most 8 files, none more than 2 folders down: a page's bundle is 3):
#
#   here:   bash benchmarks/device_wheels.sh        # once: the wheels the machine lacks, in .whl/
#   device: run(command="bash benchmarks/device_baselines.sh", carry=[".whl"], timeout_s=560)
#   here:   tar xzf <files_at>/results.tar.gz && make results docs   # then a README row each
#
# Sizing (H200, 2026-11-28): one captured TD7 seed steps 328 env steps/s on an idle GPU; three TD7
# populations of 3 side by side kept it 99% busy and none reached 100k steps in 420 s. So TD7 runs
# one population per call (JOBS=1); the cheaper captured updates (TD3, DDPG, SAC) take more.
#
# A pair whose page results/ already holds is skipped, so each GPU call takes the next ones in
# PAIRS' order. Every job stops itself (SIGINT: its runs end KILLED) DEADLINE seconds after the
# start, so a slow machine brings home what finished instead of nothing; KILLED runs stay there.
# Settings, by environment variable: PAIRS ("algo:env ..."), JOBS (at once), STEPS, DEADLINE (s),
# DEVICE (cuda; cpu tries the script here at a tiny STEPS), EXTRA (more overrides of every job, e.g.
# "eval_every=1000 algo.learning_starts=1000" for such a try), SETUP (0 skips device_venv.sh),
# RESULTS (the folder of pages that exist already: results/).
set -uo pipefail
export PYTHONUNBUFFERED=1 MUJOCO_GL=${MUJOCO_GL:-disable}
REPO=$PWD
OUT=${OUT:-/tmp/device_baselines}
RESULTS=${RESULTS:-$REPO/results}  # the pages there already
# The costliest on a CPU first (TD7 about 4x TD3's time per step, CrossQ's 2048-wide critics about 10x): the
# 2-core machines take the cheap ones (make baseline).
PAIRS=${PAIRS:-"td7:walker2d td7:hopper td7:half_cheetah crossq:hopper crossq:half_cheetah sac:walker2d sac:half_cheetah ddpg:walker2d ddpg:hopper ddpg:half_cheetah"}
JOBS=${JOBS:-1}
STEPS=${STEPS:-100000}
DEADLINE=${DEADLINE:-440}
DEVICE=${DEVICE:-cuda}
EXTRA=${EXTRA:-}
WORK=$(mktemp -d)  # stores, checkpoints and Hydra's folders: only the pages travel
trap 'rm -rf "$WORK"' EXIT  # however the call ends
mkdir -p "$OUT/results"
if [[ ${SETUP:-1} == 1 ]]; then
  bash benchmarks/device_venv.sh > "$OUT/setup.log" 2>&1 || { tail -20 "$OUT/setup.log"; exit 1; }
fi
py=$REPO/.venv/bin/python
commit=$(git rev-parse --short HEAD 2>/dev/null || echo "unknown (the tree's walkers.code_digest tag names it)")
machine="$($py -c "import torch; print(torch.cuda.get_device_name() if torch.cuda.is_available() else 'CPU')"), $(getconf _NPROCESSORS_ONLN) cores"
steps_k=$((STEPS / 1000))k

todo=()
for pair in $PAIRS; do
  name=${pair%%:*}_${pair##*:}_$steps_k
  [[ -f $RESULTS/$name/page.yaml ]] || todo+=("$pair")
done
todo=("${todo[@]:0:$JOBS}")
echo "device_baselines: ${todo[*]:-nothing left} on $machine, $STEPS steps, until ${DEADLINE}s"

train() {  # train ALGO ENV: its 3 seeds as one population, into a store of its own
  local algo=$1 env=$2 name=$1_$2_$steps_k
  cd "$WORK" && PYTHONPATH=$REPO timeout -s INT -k 45 "$DEADLINE" "$py" -m walkers.train \
    algo="$algo" env="$env" population=3 seed=0 total_steps="$STEPS" device="$DEVICE" torch_threads=2 \
    progress=false "job_key='baseline/$algo/\${env.id}/{seed}'" \
    "tracking.run_name='baseline-$algo-\${env.id}-s{seed}'" tracking.experiment="baseline_$algo" \
    tracking.uri="sqlite:///$WORK/$name.db" work_dir="$WORK/work" $EXTRA > "$OUT/$name.log" 2>&1
  local rc=$?
  case $rc in
    0) echo "$name: trained in ${SECONDS}s" ;;
    124) echo "$name: stopped at the deadline, ${DEADLINE}s, at $(reached "$name") of $STEPS steps (its runs end KILLED, on the machine)" ;;
    *) echo "$name: train exit $rc after ${SECONDS}s (its log: $OUT/$name.log)" ;;
  esac >> "$OUT/summary.txt"
}

reached() {  # reached NAME: the env steps its runs had logged through, for sizing the next call
  "$py" -c "import sqlite3, sys; c = sqlite3.connect(sys.argv[1]); print(c.execute(\"select group_concat(value, ', ') from tags where key = 'walkers.logged_through'\").fetchone()[0] or 0)" "$WORK/$1.db" 2>/dev/null || echo "unknown"
}

page() {  # page ALGO ENV: the finished runs as results/<name>/{bundle,page.yaml}
  local algo=$1 env=$2 name=$1_$2_$steps_k env_id
  env_id=$(sed -n 's/^id: *//p' "$REPO/conf/env/$env.yaml")
  (cd "$WORK" && PYTHONPATH=$REPO "$py" -m walkers.export tracking.uri="sqlite:///$WORK/$name.db" \
    tracking.experiment="baseline_$algo" "where={env: $env_id}" out="$OUT/results/$name/bundle") \
    >> "$OUT/$name.log" 2>&1 || { echo "$name: nothing finished" >> "$OUT/summary.txt"; return; }
  cat > "$OUT/results/$name/page.yaml" <<EOF
# results/$name: what this page is and how its report is made (python -m walkers.results $name).
title: "${algo^^} on $env_id, the first $steps_k steps: a locomotion baseline (walkers' defaults${EXTRA:+, but $EXTRA}), three seeds as one population on a GPU"
budget: "$STEPS env steps per seed (of the 1M asked for), 3 seeds, trained as one population (population=3: each member is the single run of its seed); the algorithm's uniform warm-up included"
machine: "a lent $machine, device=$DEVICE (captured updates where the algorithm has them), $JOBS population(s) at a time on the one GPU, torch_threads=2"
command: "python -m walkers.train algo=$algo env=$env population=3 seed=0 total_steps=$STEPS device=$DEVICE torch_threads=2 progress=false 'job_key=\\"baseline/$algo/\${env.id}/{seed}\\"' 'tracking.run_name=\\"baseline-$algo-\${env.id}-s{seed}\\"' tracking.experiment=baseline_$algo${EXTRA:+ $EXTRA} (make baseline's keys; run by benchmarks/device_baselines.sh, one store per population)"
commit: "$commit"
date: $(date -u +%F)
compare: ["env=$env"]
EOF
  echo "$name: page written" >> "$OUT/summary.txt"
}

for pair in "${todo[@]}"; do train "${pair%%:*}" "${pair##*:}" & done
wait
for pair in "${todo[@]}"; do page "${pair%%:*}" "${pair##*:}"; done
for pair in "${todo[@]}"; do
  name=${pair%%:*}_${pair##*:}_$steps_k
  echo "=== $name"; grep -E "final/return_last10|ended|error" "$OUT/$name.log" | tail -4
done
# what comes back: summary.txt, setup.log and the two archives
tar czf "$OUT/logs.tar.gz" -C "$OUT" $(cd "$OUT" && ls ./*_"$steps_k".log 2>/dev/null) && rm -f "$OUT"/*_"$steps_k".log
if [[ -n $(ls -A "$OUT/results") ]]; then tar czf "$OUT/results.tar.gz" -C "$OUT" results; fi
rm -rf "$OUT/results"
cat "$OUT/summary.txt" 2>/dev/null

#!/usr/bin/env bash
# The one command of a lent GPU call: about 6 minutes on an H200 (2026-11-27: setup 20 s, capture 26,
# update 51, throughput 96, dt 19, envs 19, tests 153), each part under its own timeout:
#
#   here:   bash benchmarks/device_wheels.sh          # once: the wheels the machine lacks, in .whl/
#   device: run(command="bash benchmarks/device_session.sh", carry=[".whl"], timeout_s=540)
#
# Parts, in this order (all by default, or name some: `bash benchmarks/device_session.sh capture
# update`): capture (the captured update against the eager one, tests/agents/test_capture.py, and the
# streams on CUDA), population (a TD3 population of 1, 5, 16 through walkers.train itself, learning
# phase, and where its lockstep step's host time goes: benchmarks/bench_population.py), update (the TD3 update: plain, walkers eager, compiled, captured; and by
# phase), throughput (TD3/SAC/PPO, captured too, populations 1/5/16), dt, envs (env stepping on
# the machine's cores), tests (make test-gpu). Each part's log goes to $OUT (what comes back), a
# line per part to $OUT/summary.txt, and the logs' ends are printed last.
set -uo pipefail
# the image has no EGL or OSMesa library: mujoco's renderer is off there (nothing in make test-gpu renders)
export PYTHONUNBUFFERED=1 MUJOCO_GL=${MUJOCO_GL:-disable} PYTHONPATH=$PWD
OUT=${OUT:-/tmp/device_session}
mkdir -p "$OUT"
parts=${*:-capture population update throughput dt envs tests}

bash benchmarks/device_venv.sh > "$OUT/setup.log" 2>&1 || { tail -20 "$OUT/setup.log"; exit 1; }
tail -1 "$OUT/setup.log"

part() {  # part NAME SECONDS COMMAND...
  local name=$1 limit=$2 start=$SECONDS rc
  shift 2
  [[ " $parts " == *" $name "* ]] || return 0
  timeout "$limit" "$@" > "$OUT/$name.log" 2>&1
  rc=$?
  echo "$name: exit $rc after $((SECONDS - start)) s (limit $limit)" | tee -a "$OUT/summary.txt"
}
py=.venv/bin/python
part capture 90 $py -m pytest -q -p no:cacheprovider tests/agents/test_capture.py tests/test_seeding.py
part population 150 $py benchmarks/bench_population.py --device cuda --phase learning \
  --populations 1,5,16 --reps 1 --steps 3000 --log-every 500 --split
part update 75 $py benchmarks/bench_update.py --device cuda --reps 3 --phases
part throughput 130 $py benchmarks/bench_throughput.py --device cuda --only "TD3,SAC,TD7,PPO" \
  --population 1,5,16 --reps 2 --steps 200
part dt 25 $py benchmarks/bench_dt.py --devices cuda --reps 2 --steps 10
part envs 30 $py benchmarks/bench_envs.py --envs 1,4,8,16 --steps 2000 --reps 2
part tests 230 make test-gpu ARGS="-n 8 -p no:cacheprovider"

for name in $parts; do
  [[ -f "$OUT/$name.log" ]] && { echo "=== $name"; tail -c 2200 "$OUT/$name.log"; }
done
cat "$OUT/summary.txt"

#!/usr/bin/env bash
# Here, before a lent GPU call: fetch into .whl/ (git-ignored) the wheels of walkers' dependencies
# that the GPU machine's image lacks, for its Python 3.12, within the call's 64 MiB. The image's own
# packages (torch, numpy, pandas, scipy, ...) are left out by name; so are mlflow's web UI (the
# `mlflow` wheel: mlflow-skinny holds the tracking API and the sqlite store), mujoco-studio (the
# viewer). Then: run(command="bash benchmarks/device_session.sh", carry=[".whl"]).
set -euo pipefail
PYV=${PYV:-3.12}
platforms=()
for p in manylinux_2_35 manylinux_2_34 manylinux_2_31 manylinux_2_28 manylinux_2_27 manylinux_2_24 \
  manylinux_2_17 manylinux2014 manylinux1; do platforms+=(--platform "${p}_x86_64"); done
tmp=$(mktemp -d)
python3 -m pip download -q -d "$tmp" --only-binary=:all: --python-version "$PYV" \
  --implementation cp "${platforms[@]}" \
  gymnasium==1.4.0 mujoco==4.0.0 hydra-core==1.4.0rc3 hydra-joblib-launcher==1.4.0rc3 \
  omegaconf==2.4.1rc1 minari==0.5.4 mlflow==3.17.2 box2d==2.3.10
# on the image already (KINDS.md's list), or not needed there: distribution names, matched whole
skip=" torch numpy pandas scipy pyarrow matplotlib pillow packaging pyyaml tqdm typing-extensions
  requests urllib3 idna certifi charset-normalizer jinja2 markupsafe click cloudpickle absl-py etils
  fsspec filelock h5py joblib protobuf psutil six python-dateutil werkzeug markdown zipp attrs rich
  pygments markdown-it-py mdurl sympy networkx mpmath anyio h11 httpx httpcore sniffio contourpy
  cycler fonttools kiwisolver pyparsing tzdata pytz threadpoolctl scikit-learn numba llvmlite
  narwhals grpcio triton setuptools pip wheel mlflow mujoco-studio
  docker gunicorn skops huey"
skip=" $(echo $skip) "  # one space between names, and around them
rm -rf .whl && mkdir .whl
for f in "$tmp"/*.whl; do
  dist=$(basename "$f" | cut -d- -f1 | tr 'A-Z_.' 'a-z--')
  case "$dist" in cuda-* | nvidia-*) continue ;; esac
  [[ "$skip" == *" $dist "* ]] && continue
  cp "$f" .whl/
done
rm -rf "$tmp"
du -sh .whl

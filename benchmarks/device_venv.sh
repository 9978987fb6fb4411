#!/usr/bin/env bash
# On a lent GPU machine (a CUDA PyTorch in its python3, no package registry): install walkers'
# other dependencies into that python3 from the wheels carried in .whl/ (benchmarks/device_wheels.sh
# fetches them here; the machine is thrown away afterwards) and stand a two-line .venv/bin/python in
# for it, so that `make bench-gpu` and `make test-gpu` run there unchanged.
#
# Never `python3 -m venv` there: that python3 is itself a venv, whose packages a new venv does not
# see; and never write through .venv/bin/python when it may be a link: writing follows the link and
# overwrites the interpreter itself (one lease was lost so, 2026-11-27).
set -euo pipefail
# only where python3 holds a CUDA PyTorch: on a developer's machine this would replace .venv
python3 -c "import torch; assert torch.cuda.is_available()" 2>/dev/null \
  || { echo "device_venv: python3 has no CUDA PyTorch here; this is for the lent GPU machine"; exit 2; }
rm -rf .venv
python3 -m pip install -q --no-index --no-deps --no-compile --root-user-action=ignore .whl/*.whl
# walkers itself, as an editable install would register it: the tree on the path (a .pth) and its
# pyproject's entry points, through which Hydra finds walkers' sweepers: without them every -m there
# failed with "Unknown plugin class : 'walkers.plugins.PlainSweeper'" (2026-11-28). Written, not
# built: pip's editable build needs a setuptools the image may not have at pyproject's version.
python3 benchmarks/device_register.py
mkdir -p .venv/bin
printf '#!/bin/sh\nexec %s "$@"\n' "$(command -v python3)" > .venv/bin/python.new
chmod +x .venv/bin/python.new && mv .venv/bin/python.new .venv/bin/python
touch .venv/.installed
.venv/bin/python -c "import torch, gymnasium, mujoco, mlflow, hydra, minari; print('device_venv:', torch.__version__, torch.cuda.get_device_name())"
.venv/bin/python -c "from importlib.metadata import entry_points as e; print('device_venv: hydra plugins', sorted(p.name for p in e(group='hydra.plugins')))"

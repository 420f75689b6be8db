#!/usr/bin/env bash
# Set up the toolkit in ./.venv (any Linux machine with Python >= 3.11).
#
#   bash tools/setup.sh          # runtime install
#   bash tools/setup.sh --dev    # plus the test and lint tools (pytest, hypothesis, ruff)
#
# torch is installed FIRST, as torch==$NSD_TORCH_VERSION (default 2.13.0, the tested release),
# unless the venv already holds a torch that the toolkit's range accepts (then it is kept).
# Where that release comes from is pip's business: its default index serves a CUDA build on
# Linux (several GB), which the toolkit uses on a machine with an NVIDIA GPU (every command's
# `device: auto`) and which runs on the CPU elsewhere. For the small CPU-only build, point
# NSD_TORCH_INDEX at PyTorch's CPU wheel index (the address is on PyTorch's installation page):
#
#   NSD_TORCH_INDEX=<PyTorch's CPU wheel index> bash tools/setup.sh
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
TORCH_VERSION=${NSD_TORCH_VERSION:-2.13.0}
extra=""
[ "${1:-}" = "--dev" ] && extra="[dev]"

if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "error: Python >= 3.11 is needed ($PYTHON is $("$PYTHON" --version 2>&1))" >&2
    exit 1
fi
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
pip=".venv/bin/python -m pip"
quiet="--quiet --disable-pip-version-check"
if .venv/bin/python -c 'import sys, torch; v = tuple(int(x) for x in torch.__version__.split("+")[0].split(".")[:2]); sys.exit(not (2, 6) <= v < (3, 0))' 2>/dev/null; then
    echo "keeping the venv's torch ($(.venv/bin/python -c 'import torch; print(torch.__version__)'))"
elif [ -n "${NSD_TORCH_INDEX:-}" ]; then
    $pip install $quiet --index-url "$NSD_TORCH_INDEX" "torch==$TORCH_VERSION"
else
    $pip install $quiet "torch==$TORCH_VERSION"
fi
$pip install $quiet -e ".$extra"
# TrackEval (HOTA, nsd/evaluation/tracking.py) without its dependencies: its metadata asks for
# the opencv-python wheel, a second OpenCV beside opencv-python-headless (its HOTA code uses
# none); everything else it imports is a dependency of the toolkit.
$pip install $quiet --no-deps "trackeval>=1.3,<2"
if [ -n "$extra" ]; then
    # aniposelib for the calibration round-trip tests, without its opencv-contrib-python
    # (a second OpenCV) and jax (triangulation only) requirements; numba, toml: test extra
    $pip install $quiet --no-deps "aniposelib>=0.8,<0.9"
fi
.venv/bin/python - <<'PY'
import torch

import nsd

build = f"CUDA {torch.version.cuda} build" if torch.version.cuda else "CPU build"
gpu = ("device=auto uses the CUDA GPU" if torch.cuda.is_available()
       else "device=auto runs on the CPU")
print(f"set-up done: nsd-netepu {nsd.__version__}, torch {torch.__version__} ({build}; {gpu})")
PY

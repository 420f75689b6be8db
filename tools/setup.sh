#!/usr/bin/env bash
# Set up the toolkit in ./.venv on a fresh machine.
#
#   bash tools/setup.sh          # runtime install
#   bash tools/setup.sh --dev    # plus test/lint tools (hypothesis, ruff, pytest-timeout)
#
# The CPU build of torch is installed FIRST and pinned (torch==2.13.0), so that no
# later requirement can pull a CUDA build of torch (several GB) from the registry.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
extra=""
[ "${1:-}" = "--dev" ] && extra="[dev]"

if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "error: Python >= 3.11 is needed ($PYTHON is $("$PYTHON" --version 2>&1))" >&2
    exit 1
fi
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
pip=".venv/bin/python -m pip"
$pip install --quiet --disable-pip-version-check "torch==2.13.0"
$pip install --quiet --disable-pip-version-check -e ".$extra"
.venv/bin/python - <<'PY'
import torch
assert torch.__version__.startswith("2.13.0"), torch.__version__
assert not torch.version.cuda, f"a CUDA build of torch was installed ({torch.version.cuda})"
print(f"set-up done: torch {torch.__version__} (CPU), {torch.get_num_threads()} threads")
PY

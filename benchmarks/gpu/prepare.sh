#!/usr/bin/env bash
# Gathers, on a machine with pip access, the wheels that run.sh installs on a GPU machine that
# has PyTorch but no package index: hydra-core and its two dependencies, and this project's
# own wheel (rebuild it after every change: the GPU machine runs the installed examples and
# configs). They go to .whl/ in the repository root, which git ignores (.git/info/exclude).
#   bash benchmarks/gpu/prepare.sh [python version of the GPU machine, default 3.12]
set -euo pipefail
cd "$(dirname "$0")/../.."
py=${1:-3.12}
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
rm -rf .whl && mkdir -p .whl
python -m pip download -q --no-deps --only-binary=:all: --python-version "$py" \
    --implementation cp --platform any -d .whl hydra-core==1.3.8 omegaconf==2.3.1
python -m pip wheel -q --no-deps -w .whl antlr4-python3-runtime==4.9.3  # an sdist only
python -m pip wheel -q --no-deps --no-build-isolation -w .whl .
ls -la .whl

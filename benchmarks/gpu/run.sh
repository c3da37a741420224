#!/usr/bin/env bash
# The GPU checks in order, each under a time limit of its own, every figure and log to $OUT:
#   bash benchmarks/gpu/run.sh tests bench           # correctness on CUDA, then the speed tables
#   bash benchmarks/gpu/run.sh paper 6                # the paper's protocol, 6 minutes of training
# On a machine with PyTorch and CUDA but no package index: run benchmarks/gpu/prepare.sh where
# pip works, carry .whl/ along, and this installs it (nothing else) into /tmp/site.
#   tests  pytest --device cuda on the group axioms (float32, float64) and tests/test_device.py
#          (the shipped observers' rollouts and online steps, training, resume, evaluation and
#          the train command on the GPU against the CPU): tests.log, junit_device.xml
#   bench  benchmarks/gpu/bench_gpu.py: training step and inference against cuDNN: gpu_bench.json,
#          gpu.md
#   paper  experiment=paper_rigid_body on the GPU for MINUTES of training (train.time_limit),
#          best validation model evaluated on the paper's inference sets at every sigma:
#          paper_run.tgz (the run folder without last.pt), paper.log
set -u
cd "$(dirname "$0")/../.."
OUT=${OUT:-$PWD/gpu_out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 HYDRA_FULL_ERROR=1
PY=${PYTHON:-python3}
if [ -d .whl ] && ! $PY -c 'import hydra, manifold_nets_examples' 2>/dev/null; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site
fi
{
    date -u
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv
    $PY -c 'import torch; print("torch", torch.__version__, "cuda", torch.version.cuda,
"cudnn", torch.backends.cudnn.version(), torch.cuda.get_device_name())'
    nproc
} > "$OUT/device.txt" 2>&1
cat "$OUT/device.txt"

step() {  # step NAME SECONDS COMMAND...: runs with its own limit, logs to $OUT/NAME.log
    local name=$1 limit=$2
    shift 2
    echo "== $name (limit ${limit}s): $*"
    local t0=$SECONDS
    timeout --signal=INT --kill-after=20 "$limit" "$@" > "$OUT/$name.log" 2>&1
    local rc=$?
    echo "== $name: exit $rc after $((SECONDS - t0)) s" | tee -a "$OUT/summary.txt"
    tail -n 25 "$OUT/$name.log"
}

while [ $# -gt 0 ]; do
    case $1 in
    tests)
        step tests "${TESTS_LIMIT:-240}" $PY -m pytest --device cuda -q -n 8 -p no:cacheprovider \
            -o junit_family=legacy --junitxml="$OUT/junit_device.xml" \
            tests/test_group_axioms.py tests/test_device.py
        ;;
    bench)
        step bench "${BENCH_LIMIT:-330}" $PY benchmarks/gpu/bench_gpu.py \
            --json "$OUT/gpu_bench.json" --write "$OUT/gpu.md"
        ;;
    paper)
        minutes=$2
        shift
        # the inference sets on the CPU while the GPU trains (the train command would otherwise
        # make them one by one after training)
        ( $PY -m manifold_nets.cli.generate -m dataset=paper_inference \
            dataset.sigma=0.1,0.2,0.3,0.4,0.5 hydra.sweep.dir=/tmp/generate > "$OUT/generate.log" 2>&1 & )
        step paper $(( ${minutes%.*} * 60 + 240 )) $PY -m manifold_nets.cli.train \
            experiment=paper_rigid_body train.device=cuda train.time_limit="$minutes" \
            train.progress=false ${PAPER_OVERRIDES:-} hydra.run.dir=/tmp/paper_run
        tar --exclude=last.pt -czf "$OUT/paper_run.tgz" -C /tmp paper_run
        ;;
    *) echo "unknown step $1 (tests, bench, paper MINUTES)"; exit 2 ;;
    esac
    shift
done

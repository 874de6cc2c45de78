#!/usr/bin/env bash
# The checks a CUDA machine is for, in one go (docs/BENCHMARKS.md, "On a GPU"): build the kernels, run
# the gpu tests, then the GPU rows of tools/bench_render.py, tools/bench_avatar.py and
# tools/tradeoff.py. GPU time is scarce, so every step has its own time limit, a failing step
# does not stop the next, and each writes its log into OUTDIR as it goes.
#
#     tools/gpu_checks.sh OUTDIR
#
# Needs the project's dependencies and gsplat importable (pip install -e '.[cuda,dev]', or
# wheels on PYTHONPATH: the measuring children keep it).
# The trade-off row trains the fast preset on the dance subject on the GPU; the same row on this
# machine's CPU (one thread, CUDA hidden) trains beside the GPU steps as the same-run baseline.
set -u
out=${1:?usage: tools/gpu_checks.sh OUTDIR}
mkdir -p "$out"
cd "$(dirname "$0")/.."
py=${PYTHON:-python3}
export STG_THREADS=${STG_THREADS:-1} PYTHONUNBUFFERED=1
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-$("$py" -c \
    'import torch; print("%d.%d" % torch.cuda.get_device_capability())' 2>/dev/null)}
work=${GPU_CHECKS_WORK:-/tmp/stg_gpu_checks}
mkdir -p "$work" && rm -f "$work/data.ready"

step() {  # step NAME LIMIT_S COMMAND...: run with a time limit, log to OUTDIR/NAME.log
    local name=$1 limit=$2 start=$SECONDS rc
    shift 2
    echo "== $name (limit ${limit}s): $*"
    timeout -k 5 "$limit" "$@" >"$out/$name.log" 2>&1
    rc=$?
    echo "== $name: exit $rc after $((SECONDS - start)) s"
    tail -n 25 "$out/$name.log"
}

nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
"$py" -c 'import torch; print("torch", torch.__version__, "cuda", torch.version.cuda)'

tradeoff_args=(--only preset_fast --data-cache "$work/data" --no-progress)
(   # the CPU side: its kernels, the subject, then the CPU baseline row of the trade-off
    "$py" -m stg_node.cli.splat_prebuild --backend cpu
    "$py" -c "import sys; sys.path.insert(0, 'tools'); from pathlib import Path; import tradeoff as t; \
t.ensure_subject(Path('$work/data'), 'dance', t.FULL)" && touch "$work/data.ready"
    CUDA_VISIBLE_DEVICES= timeout -k 5 "${CPU_BASELINE_LIMIT:-420}" "$py" tools/tradeoff.py \
        "${tradeoff_args[@]}" --device cpu --backend cpu --out "$work/cpu" \
        --docs "$work/cpu/BENCHMARKS.md" --plot "$work/cpu/pareto.png"
) >"$out/cpu_side.log" 2>&1 &
cpu_side=$!
(   # the posed-avatar bench's subject, generated outside that step's time limit
    "$py" -c "import sys; sys.path.insert(0, 'tools'); import bench_avatar as b; b.ensure_data(None)"
) >"$out/avatar_data.log" 2>&1 &
avatar_data=$!

step prebuild "${PREBUILD_LIMIT:-240}" "$py" -m stg_node.cli.splat_prebuild --backend cuda
# Only the modules that hold gpu tests: collecting the rest needs every runtime dependency (depthai,
# foxglove, LiteRT), which a GPU image may lack, and none of them has a gpu test.
mapfile -t gpu_modules < <(grep -rlE "mark\.gpu" tests --include='test_*.py' | sort)
step pytest_gpu "${PYTEST_LIMIT:-120}" "$py" -m pytest -m gpu -q -p no:cacheprovider "${gpu_modules[@]}"
step bench_render "${RENDER_LIMIT:-90}" "$py" tools/bench_render.py --threads 1 --repeats 10 --no-torch
wait "$avatar_data"  # a minute of CPU, begun with the kernels' build
step bench_avatar "${AVATAR_LIMIT:-200}" "$py" tools/bench_avatar.py --device cuda --rounds 1 --steps 30 \
    --no-baseline --only step render --json "$out/bench_avatar.json"
wait_for=$((SECONDS + 120))
until [ -e "$work/data.ready" ] || [ $SECONDS -gt $wait_for ]; do  # the CPU side generates it
    sleep 2
done
step tradeoff_gpu "${TRADEOFF_LIMIT:-240}" "$py" tools/tradeoff.py "${tradeoff_args[@]}" \
    --device cuda --backend cuda --out "$work/gpu" --docs "$work/gpu/BENCHMARKS.md" --plot "$work/gpu/pareto.png"
wait "$cpu_side"
echo "== cpu side: exit $?"
tail -n 15 "$out/cpu_side.log"
tar -czf "$out/tradeoff_results.tgz" -C "$work" --exclude='*.ckpt' --exclude='*.msgpack' \
    gpu/results cpu/results gpu/BENCHMARKS.md cpu/BENCHMARKS.md 2>/dev/null
echo "== done"

#!/usr/bin/env bash
# The GPU checks of this toolkit as one call on a lent GPU machine (the workplace's `device`
# tool: one H100 or H200, 16 cores, torch with CUDA, none of our other dependencies, no
# network, ~15 minutes of device time per task). Two steps:
#
#   bash bench/device_check.sh prepare     # here: wheels into .whl/, EGL libraries into .gl/
#   bash bench/device_check.sh run         # there: device.run(command="bash bench/device_check.sh run",
#                                          #                   carry=[".whl", ".gl"], timeout_s=590)
#
# `run` installs the carried wheels, then, each phase under its own time limit so that one
# call ends inside the tool's 10 minutes and leaves what it measured under $OUT:
#   1. the tests marked `gpu` (tests/test_gpu.py): a smoke curriculum per model on CUDA, a run
#      killed and resumed under EWC and PackNet, compiled hot paths and CUDA graphs equal to
#      eager, bench/update_rate.py on CUDA;
#   2. bench/update_rate.py at `paper`, state, on the GPU, one model and mode per process in
#      the order wanted most (`BENCH_ORDER`: what is not measured yet first) until the
#      phase's four minutes are spent.
# $OUT gets gpu.csv, gpu_tests.log, update_rate.jsonl (one bench JSON a line) and
# update_rate.err (the tool brings back 8 files at most); the last lines printed summarise.
# The official TD-MPC2 with compile=true on the same GPU (issue 19's anchor) is not part of
# this script: its code is not ours to carry in the repository (on 2026-11-27 a scratch harness
# timed it in the same call; docs/performance.md, "On a GPU").
set -uo pipefail
cd "$(dirname "$0")/.."
WHEELS=(draccus mergedeep toml typing-inspect mujoco metaworld gymnasium farama-notifications
        glfw pyopengl dill pytz)
GL_DEBS=(libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
# Measured on an H200 on 2026-11-27: TD-MPC2 eager and graphs, DreamerV3 eager (docs/performance.md). Next:
# what would decide `compile_pays` on CUDA and the paper preset's bf16, and `graphs` again
# as the loop now runs it (outputs copied).
BENCH_ORDER=("tdmpc2 compiled" "tdmpc2 graphs" "tdmpc2 auto-bf16" "tdmpc2 graphs-bf16"
             "dreamerv3 auto-bf16" "dreamerv3 compiled" "tdmpc2 eager" "dreamerv3 eager" "pwm eager"
             "pwm graphs" "pwm graphs-bf16")

prepare() {
    local py=.venv/bin/python freeze pins=()
    test -x "$py" || { echo "device_check: no .venv here (make install first)" >&2; exit 2; }
    freeze=$(.venv/bin/uv pip freeze --python "$py" 2>/dev/null || "$py" -m pip freeze)
    for name in "${WHEELS[@]}"; do  # the versions this checkout's tests pass with
        pin=$(grep -i "^${name//-/[-_]}==" <<<"$freeze" || true)
        [ -n "$pin" ] || { echo "device_check: $name is not installed in .venv" >&2; exit 2; }
        pins+=("$pin")
    done
    for d in .whl .gl; do grep -qx "/$d/" .git/info/exclude 2>/dev/null || echo "/$d/" >>.git/info/exclude; done
    rm -rf .whl && mkdir -p .whl
    "$py" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
        --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        --platform manylinux1_x86_64 -d .whl "${pins[@]}" || exit 2
    local apt_opts=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
    rm -rf .gl && mkdir -p .gl /tmp/amd64/partial
    apt-get "${apt_opts[@]}" update -qq && (cd .gl && apt-get "${apt_opts[@]}" download -qq "${GL_DEBS[@]}") || exit 2
    du -sh .whl .gl
    echo "device_check: the working tree travels with them; the tool's limit is 64 MiB in all:"
    echo "  $(( $(git ls-files -z | xargs -0 du -cb | tail -1 | cut -f1) / 1048576 )) MiB tracked + .whl + .gl"
}

run() {
    [ -n "${OUT:-}" ] || { echo "device_check: run it on the device machine, where \$OUT is set" >&2; exit 2; }
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl || exit 2
    export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl PYTHONUNBUFFERED=1
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv | tee "$OUT/gpu.csv"
    python3 -c 'import torch; print("torch", torch.__version__, torch.cuda.get_device_name())'

    echo "== 1. tests marked gpu"
    # One worker per test: on an H200 machine 12 took 194 s so, the longest (the bench's
    # CUDA-graph compile of every model) 180 s; six workers did not finish in 220 s.
    timeout 240 python3 -m pytest -v -m gpu -p no:cacheprovider -n 16 --durations=5 \
        tests/test_gpu.py 2>&1 | tee "$OUT/gpu_tests.log" | grep -E "PASSED|FAILED|ERROR|passed|failed|s call"

    echo "== 2. bench/update_rate.py at paper on the GPU"
    # One model and mode per process: one killed by the phase's limit loses its row alone.
    local deadline=$((SECONDS + 240)) spec left
    for spec in "${BENCH_ORDER[@]}"; do
        left=$((deadline - SECONDS))
        [ "$left" -gt 20 ] || break
        set -- $spec
        echo "$spec (${left} s left)"
        timeout "$left" python3 bench/update_rate.py --models "$1" --presets paper \
            --variants state --modes "$2" --repeats 20 --warmup 3 --device cuda \
            >"$OUT/row.json" 2>>"$OUT/update_rate.err" \
            && python3 -c 'import json, sys; print(json.dumps(json.load(open(sys.argv[1]))))' \
                "$OUT/row.json" >>"$OUT/update_rate.jsonl"
    done
    rm -f "$OUT/row.json"
    summary
}

summary() {
    echo "== summary (ms per update / per act; the bench's whole JSON in \$OUT/update_rate.jsonl)"
    grep -E "passed|failed|skipped|error" "$OUT/gpu_tests.log" | tail -1
    python3 - "$OUT/update_rate.jsonl" <<'PYEOF'
import json, sys
from pathlib import Path
path = Path(sys.argv[1])
for line in path.read_text().splitlines() if path.exists() else []:
    for r in json.loads(line)["results"]:
        print(f"{r['model']:9} {r['preset']:6} {r['mode']:12} "
              f"update {1e3 * r['update_s_median']:8.2f}  act {1e3 * r['act_s_median']:8.2f}")
PYEOF
}

case "${1:-run}" in
    prepare) prepare ;;
    run) run ;;
    *) echo "usage: bash bench/device_check.sh prepare|run" >&2; exit 2 ;;
esac

#!/usr/bin/env bash
# GPU checks of inference latency, run from the repository root on a machine with CUDA:
#   (1) python -m benchmarks export --device cuda: eager, CUDA graphs and inductor per chunk
#       -> $OUT/export/export_gpu.json and the GPU section of $OUT/export/export.md
#   (2) the speed suite's sampler-overhead section on CUDA -> $OUT/suite/ (README.md, results.json)
#   (3) trained and guided RTC chunk against a plain chunk, B = 1 -> $OUT/rtc_latency_cuda.json
#   (4) the RTC page's chunk-cost part (plain against trained, B = 1) -> $OUT/rtc_cost_cuda.json
# Each step runs under its own `timeout`; a failed or timed-out step does not stop the next.
#
#   PYTHONPATH=$PWD/src:$PWD bash scripts/gpu_check.sh          # on the GPU machine
#   DEVICE=cpu OUT=/tmp/gpu_check bash scripts/gpu_check.sh     # CPU fallback: tiny sizes, same steps
#
# Environment: OUT (default ./outputs/gpu), DEVICE (cuda | cpu, default cuda), ROUNDS (export's rounds).
# Wheels in ./.whl (e.g. diffusers, needed by the DDPM cases and the suite) are installed into /tmp/site
# (SKIP_WHEELS=1: they are installed already and on PYTHONPATH).
set -u
OUT=${OUT:-./outputs/gpu}
DEVICE=${DEVICE:-cuda}
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
export PYTHONPATH="$PWD/src:$PWD${PYTHONPATH:+:$PYTHONPATH}"
if [ -z "${SKIP_WHEELS:-}" ] && compgen -G ".whl/*.whl" >/dev/null; then
    echo "== installing $(ls .whl/*.whl | wc -l) wheel(s) from .whl into /tmp/site"
    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl \
        && export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi
mkdir -p "$OUT"

if [ "$DEVICE" = cuda ]; then
    EXPORT_ARGS=(--cases mean_flow:1,flow_matching:10,DDPM:10,mean_flow:2,flow_matching:1 --batches 1,32
                 --rounds "${ROUNDS:-20}" --warmup 3 --build-budget-s 70)   # cut last: the least telling cases
    SUITE_ARGS=(--quick)
    RTC_ARGS=(--rounds 20)
    COST_ARGS=(--latency-reps 100)
    T_EXPORT=170 T_SUITE=60 T_RTC=45 T_COST=45
else                                     # the CPU fallback: tiny networks, the same code paths
    EXPORT_ARGS=(--tiny --cases mean_flow:1,flow_matching:10 --batches 1 --rounds "${ROUNDS:-2}" --warmup 1)
    SUITE_ARGS=(--tiny)
    RTC_ARGS=(--tiny --rounds 3 --warmup 1)
    COST_ARGS=(--latency-reps 3)
    T_EXPORT=600 T_SUITE=300 T_RTC=120 T_COST=120
fi

python3 - <<'EOF'
import platform, torch
gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU"
print(f"== torch {torch.__version__}, Python {platform.python_version()}, {gpu}")
try:
    import diffusers
    print(f"== diffusers {diffusers.__version__}")
except ImportError:
    print("== diffusers not importable: the DDPM cases and the suite's DDPM rows will fail")
EOF

SUMMARY="$OUT/summary.txt"
: > "$SUMMARY"
step() {                                  # step NAME TIMEOUT_S CMD...
    local name=$1 limit=$2; shift 2
    echo "== $name (timeout ${limit} s): $*"
    local t0=$SECONDS
    timeout "$limit" "$@" 2>&1 | tee "$OUT/$name.log"
    local rc=${PIPESTATUS[0]}
    echo "$name: rc=$rc, $((SECONDS - t0)) s" | tee -a "$SUMMARY"
}

step export "$T_EXPORT" python3 -m benchmarks export --device "$DEVICE" --out "$OUT/export" "${EXPORT_ARGS[@]}"
step suite_sampling "$T_SUITE" python3 -m benchmarks --device "$DEVICE" --sections sampling --no-plot \
    --out "$OUT/suite" "${SUITE_ARGS[@]}"
step rtc_latency "$T_RTC" python3 -m benchmarks rtc-latency --device "$DEVICE" --out "$OUT/rtc_latency_$DEVICE.json" \
    "${RTC_ARGS[@]}"
step rtc_cost "$T_COST" python3 -m benchmarks rtc --part cost --device "$DEVICE" --cost-json "$OUT/rtc_cost_$DEVICE.json" \
    "${COST_ARGS[@]}"
echo "== summary ($OUT)"
cat "$SUMMARY"

#!/usr/bin/env bash
# The GPU checks that the CPU benchmarks leave open, in one call of a few minutes:
#  * issue 3: breakage screening of a settled 1,100-grain pile against one contact step of it
#    (target: <= 25 % of a step; bench_screening.py), float32 and float64;
#  * issue 8: K bonded Brazilian discs in one vmapped batch against K runs one after another
#    (target: >= 8x at K = 64; bench_ensemble.py).
#
#   OUT=/tmp/out bash benchmarks/device_checks.sh
#
# Writes under $OUT (six files, inside the device tool's eight): gpu.txt (device, versions),
# SCREENING_GPU.md/.json and screening.log, ensemble_gpu.json and ensemble.log. Each bench
# gets its own time limit (T_SCREEN, T_ENS seconds). SCREEN_CACHE names a pickle of the
# settled pile (bench_screening.py --cache) carried along, to skip the settling;
# SCREEN_ARGS and ENS_ARGS pass more options (e.g. smaller sizes for a dry run on a CPU).
set -u
OUT=${OUT:?set OUT}
T_SCREEN=${T_SCREEN:-300}
T_ENS=${T_ENS:-240}
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 MPLBACKEND=Agg
export JAX_PLATFORMS=${JAX_PLATFORMS:-cuda} XLA_PYTHON_CLIENT_PREALLOCATE=false
mkdir -p "$OUT"
{
  date -u
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  python3 -c "import jax; print('jax', jax.__version__, jax.devices())"
} > "$OUT/gpu.txt" 2>&1
timeout "$T_SCREEN" python3 benchmarks/bench_screening.py --out "$OUT/SCREENING_GPU" \
  ${SCREEN_CACHE:+--cache "$SCREEN_CACHE"} ${SCREEN_ARGS:-} > "$OUT/screening.log" 2>&1
echo "screening rc $?" >> "$OUT/gpu.txt"
timeout "$T_ENS" python3 benchmarks/bench_ensemble.py --json "$OUT/ensemble_gpu.json" ${ENS_ARGS:-} \
  > "$OUT/ensemble.log" 2>&1
echo "ensemble rc $?" >> "$OUT/gpu.txt"
tail -n 20 "$OUT/screening.log" "$OUT/ensemble.log" >> "$OUT/gpu.txt"
cat "$OUT/gpu.txt"

#!/usr/bin/env bash
# The four methods of the Voronoi oedometer comparison (issue 5), one process each, at once
# on one GPU, for at most LIMIT seconds of wall time; each process checkpoints every
# CKPT_MIN minutes, so an unfinished run goes on later from its checkpoint (here or on a CPU:
# benchmarks/run_voronoi_oedometer.py with the same --bar-speed/--load-time resumes it).
#
#   OUT=/tmp/out LIMIT=470 bash benchmarks/device_voronoi_oedometer.sh
#
# Writes, under $OUT: <method>.tgz (the run folder, checkpoint or summary + run.h5 + figures
# once finished, and the run's log) and gpu.txt (device, versions, wall time, last progress
# lines): five files, inside the device tool's limit of eight.
# To go on with runs of this machine's runs/voronoi_30mm there: pack each run folder as
#   mkdir -p voronoi_carry; echo /voronoi_carry/ >> .git/info/exclude
#   for m in dsm split-cell cross-cut mohr-coulomb; do
#     tar czf voronoi_carry/$m.tgz -C runs/voronoi_30mm $m; done
# and name voronoi_carry in the device call's carry; back here, unpack the returned
# <method>.tgz into runs/voronoi_30mm and rerun run_voronoi_oedometer.py (it collects).
# FORK_FROM=dsm starts the methods without a checkpoint from that method's checkpoint
# (taken before any breakage; oedometer_cantor.fork_checkpoint), before any run goes on.
# Runs the repository's own jaxgran from the source tree (PYTHONPATH): the machine's Python
# has jax and the other dependencies but nothing can be installed there.
set -u
OUT=${OUT:?set OUT}
LIMIT=${LIMIT:-470}
CKPT_MIN=${CKPT_MIN:-1}
BAR_SPEED=${BAR_SPEED:-0.003}
LOAD_TIME=${LOAD_TIME:-10}
METHODS=${METHODS:-"dsm split-cell cross-cut mohr-coulomb"}
RUNS=${RUNS:-/tmp/voronoi_runs}
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 MPLBACKEND=Agg
export JAX_PLATFORMS=${JAX_PLATFORMS:-cuda} XLA_PYTHON_CLIENT_PREALLOCATE=false
mkdir -p "$RUNS" "$OUT"
# runs carried from an earlier call or from this machine: voronoi_carry/<method>.tgz as
# written below (a checkpoint compresses about 5x), named in the device call's carry
for f in voronoi_carry/*.tgz; do [ -e "$f" ] && tar xzf "$f" -C "$RUNS"; done
{
  date -u
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  python3 -c "import jax, numpy; print('jax', jax.__version__, 'numpy', numpy.__version__, jax.devices())"
  echo "bar_speed=$BAR_SPEED load_time=$LOAD_TIME limit=$LIMIT s methods=$METHODS"
} > "$OUT/gpu.txt" 2>&1
ARGS=(--runs "$RUNS" --dest "$RUNS/collected" --bar-speed "$BAR_SPEED" --load-time "$LOAD_TIME")
[ -n "${QUICK:-}" ] && ARGS+=(--quick)
if [ -n "${FORK_FROM:-}" ]; then
  python3 benchmarks/run_voronoi_oedometer.py "${ARGS[@]}" --collect-only \
    --fork-from "$FORK_FROM" >> "$OUT/gpu.txt" 2>&1
fi
start=$(date +%s)
for m in $METHODS; do
  timeout "$LIMIT" python3 benchmarks/run_voronoi_oedometer.py --methods "$m" "${ARGS[@]}" \
    --checkpoint-minutes "$CKPT_MIN" > "$RUNS/$m.log" 2>&1 &
done
wait
echo "wall $(( $(date +%s) - start )) s" >> "$OUT/gpu.txt"
for m in $METHODS; do
  [ -d "$RUNS/$m" ] && tar czf "$OUT/$m.tgz" -C "$RUNS" "$m" "$m.log"
  # the last progress line of each run, for the steps/s
  tr '\r' '\n' < "$RUNS/$m.log" | grep -a "step/s" | tail -1 | sed "s/^/$m: /" >> "$OUT/gpu.txt"
  tr '\r' '\n' < "$RUNS/$m.log" | grep -av "step/s" | tail -3 >> "$OUT/gpu.txt"
done
ls -la "$OUT" >> "$OUT/gpu.txt"
cat "$OUT/gpu.txt"

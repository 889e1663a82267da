#!/bin/bash
# The full-size discovery benchmark from images on a GPU machine: one shard per scene, stage 0 and
# its continuum on the GPUs (round robin), base fit and discovery on one CPU core each.
#
#   bash benchmarks/discovery_from_images.sh OUT [SHARDS] [STAGE0_ITERATIONS]
#
# Shards run in the background (logs in OUT/logs); when every shard has exited, tabulate with
#   python benchmarks/discovery.py --report-only --calibrate --geometry stage0 --stage0 "$(cat OUT/stage0.json)" --out OUT
# A rerun skips finished scenes (OUT/results_*.jsonl) and reuses finished stage 0s.
# Environment: SEED (stage 0's seed, default 0; one OUT per seed, compared by
# benchmarks/discovery_runs.py), THRESHOLDS (a thresholds JSON used while running, e.g. those
# calibrated on an earlier run's null scenes; default: the shipped ones; --report-only
# --calibrate decides again on this run's null scenes either way), RANGE=A:B (launch only shards
# A..B-1 of the N, e.g. RANGE=0:30 then RANGE=30:60 on two machines or leases: one shard per core
# keeps every base fit at full speed; the same OUT gathers both halves).
set -eu
OUT=${1:?usage: discovery_from_images.sh OUT [SHARDS] [STAGE0_ITERATIONS]}
N=${2:-60}
ITERS=${3:-2500}
EXTRA=(--stage0-seed "${SEED:-0}")
if [ -n "${THRESHOLDS:-}" ]; then
  [ -f "$THRESHOLDS" ] || { echo "THRESHOLDS=$THRESHOLDS: no such file (expected a thresholds JSON)" >&2; exit 2; }
  EXTRA+=(--thresholds "$THRESHOLDS")
fi
RANGE=${RANGE:-0:$N}
A=${RANGE%%:*}; B=${RANGE##*:}
if ! [[ "$A" =~ ^[0-9]+$ && "$B" =~ ^[0-9]+$ ]] || [ "$A" -ge "$B" ] || [ "$B" -gt "$N" ]; then
  echo "RANGE=$RANGE: expected A:B with 0 <= A < B <= $N (shards A..B-1 of $N)" >&2
  exit 2
fi
NG=$(nvidia-smi -L 2>/dev/null | wc -l)
if [ "$NG" -lt 1 ]; then
  echo "no GPU found (nvidia-smi -L): stage 0 at full size needs one" >&2
  exit 2
fi
mkdir -p "$OUT/logs"
python -c "import json; from toolkit.scene.stage0 import compressed_settings; print(json.dumps(compressed_settings($ITERS)))" > "$OUT/stage0.json"
S0=$(cat "$OUT/stage0.json")
for i in $(seq "$A" $((B - 1))); do
  CUDA_VISIBLE_DEVICES=$((i % NG)) OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 setsid nohup python benchmarks/discovery.py \
    --geometry stage0 --stage0 "$S0" --stage0-device cuda --device cpu --no-reports --shard "$i/$N" --out "$OUT" "${EXTRA[@]}" \
    > "$OUT/logs/shard_$i.log" 2>&1 < /dev/null &
done
echo "launched shards $A..$((B - 1)) of $N on $NG GPUs and $(nproc) cores; logs in $OUT/logs"

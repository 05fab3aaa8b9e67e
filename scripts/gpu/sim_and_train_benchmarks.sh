#!/usr/bin/env bash
# GPU: the sim benchmark at paper scale (2,592 clips batched vs one at a time) and the
# training benchmark (eager fp32 vs bf16 + compile + channels_last). Results -> $OUT.
set -uo pipefail
source scripts/gpu/env.sh
python3 benchmarks/sim_throughput.py --device cuda --n 2592 --baseline 8 --frames 40 2>&1 | tail -20
cp benchmarks/results/sim_throughput-cuda* "$OUT"/ 2>/dev/null
python3 benchmarks/train_throughput.py --device cuda --steps 30 --warmup 10 2>&1 | tail -20
cp benchmarks/results/train_throughput-cuda* "$OUT"/ 2>/dev/null

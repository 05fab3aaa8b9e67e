#!/usr/bin/env bash
# GPU: what self-collision costs per setting at the paper's scale (2,592 wind clips x 40 frames each,
# off then on, the paper preset's batches). SETTINGS=wind-uniform1,wind-uniform2,... for more settings.
# Writes benchmarks/results/sim_self_collision-cuda-n2592.json (copied to $OUT).
set -uo pipefail
source scripts/gpu/env.sh
SETTINGS=${SETTINGS:-wind-uniform1}
python3 benchmarks/sim_self_collision.py --device cuda --settings "$SETTINGS" ${EXTRA:-} \
  --out "$OUT/sim_self_collision-cuda-n2592.json"

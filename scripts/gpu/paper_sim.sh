#!/usr/bin/env bash
# GPU: simulate the paper's uniform-level-1 datasets (2,592 wind + 2,592 arm clips)
# through the sim stage, as a user would. Timings -> $OUT/paper_sim.json.
set -uo pipefail
source scripts/gpu/env.sh
RUN=${RUN:-/tmp/paper}
SETTINGS=${SETTINGS:-uniform1}
/usr/bin/time -v python3 -m clothgap sim --preset paper --out "$RUN" --set sim.remeshing=$SETTINGS \
  --set sim.batch_size=2592 2> "$OUT/paper_sim.time" | tail -5
grep -E "Elapsed|Maximum resident" "$OUT/paper_sim.time"
cp "$RUN"/config.json "$OUT"/paper_config.json
du -sh "$RUN"/sim/*

#!/usr/bin/env bash
# GPU: the domain-gap study (issue 15) on one setting at the paper preset, through the real CLI: one
# simulation, rendered under `paper` and variants that each change one render axis, one lrcn per variant
# (the preset's recipe), every model tested on every variant (paired test clips), the measured fabrics.
#   STAGES="sim render" LIMIT=540 bash scripts/gpu/domain_gap.sh      then STAGES=render (resumes), then
#   STAGES="train eval report" ...
# N sequences per class (default 12: 648 clips, 108 test sequences); VARIANTS comma-separated.
# Every stage resumes, so a call cut at LIMIT seconds loses at most the clip or epoch in flight.
# Writes $OUT/domain_gap.tgz (config, timings, eval tables, report) and $OUT/domain_gap.log.
set -uo pipefail
source scripts/gpu/env.sh
RUN=${RUN:-/tmp/gap}; N=${N:-12}; MOTIONS=${MOTIONS:-wind}
VARIANTS=${VARIANTS:-paper,grid,diffuse,lighting-random,room,filmic,camera-noise,motion-blur,heldout}
STAGES=${STAGES:-"sim render train eval report"}
SETS=(--set sim.motions=$MOTIONS --set sim.remeshing=uniform1 --set sim.sequences_per_class=$N
      --set sim.batch_size=$((N * 54)) --set render.variants=$VARIANTS --set train.models=lrcn ${EXTRA:-})
for stage in $STAGES; do
  t0=$(date +%s.%N)
  if [ -f "$RUN/config.json" ]; then args=("$RUN"); else args=(--preset paper --out "$RUN" "${SETS[@]}"); fi
  ${LIMIT:+timeout -k 10 "$LIMIT"} python3 -m clothgap $stage "${args[@]}" 2>&1 | tr '\r' '\n' \
    | grep -vE "it/s\]|clip/s\]|shard/s\]|s/it\]" | tail -8 | tee -a "$OUT/domain_gap.log"
  rc=${PIPESTATUS[0]}
  python3 -c "import json; print(json.dumps({'stage': '$stage', 'rc': $rc, 'seconds': round($(date +%s.%N)-$t0, 1)}))" \
    | tee -a "$RUN/gpu_timings.jsonl"
done
cd "$RUN" && tar czf "$OUT/domain_gap.tgz" config.json gpu_timings.jsonl \
  $(ls train/*/*/*/s*/metrics.csv eval/*.csv eval/*.md eval/*.json report/report.html 2>/dev/null) 2>/dev/null
ls -la "$OUT"

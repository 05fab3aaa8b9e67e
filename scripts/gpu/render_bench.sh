#!/usr/bin/env bash
# GPU: render throughput at 224 and 112 px, 16 spp (benchmarks/render_throughput.py), plain and with
# frozen renders in the multi-process rows. Results -> $OUT and /tmp/keep (for later calls on the same machine).
set -uo pipefail
source scripts/gpu/env.sh
mkdir -p /tmp/keep
for res in ${RESOLUTIONS:-224 112}; do
  python3 benchmarks/render_throughput.py --device cuda --resolution $res --spp 16 --clips ${CLIPS:-40} --frames 40 \
    --procs ${PROCS:-2,4} --out "$OUT/render_throughput-cuda-$res.json" 2>&1 | grep -vE "^\s" | grep -v "^\{" | tail -12
  ok=$(python3 -c "import json; d=json.load(open('$OUT/render_throughput-cuda-$res.json')); print(str(d['rounds'][0].get('frozen_rel_error', 1) < 1e-4).lower())")
  echo "frozen exact at $res: $ok"; echo $ok > /tmp/keep/freeze_ok_$res
  if [ "$ok" = true ]; then
    python3 benchmarks/render_throughput.py --device cuda --resolution $res --spp 16 --clips ${CLIPS:-40} --frames 40 \
      --procs ${PROCS:-2,4} --procs-freeze --out "$OUT/render_throughput-cuda-$res-frozen.json" 2>&1 | grep -E "^processes" | tail -4
  fi
done
cp $OUT/*.json /tmp/keep/

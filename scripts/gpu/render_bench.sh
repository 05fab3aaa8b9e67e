#!/usr/bin/env bash
# GPU: render throughput at 224 and 112 px, 16 spp (benchmarks/render_throughput.py) as ratios to the path
# tracer's ceiling measured in the same run: render-only loops, then the stage's render_clip writing frames.npy
# alone (the paper preset) and with PNG + EXR (what every clip wrote before), in one process and in
# $WRITE_PROCS processes; plain and with frozen renders in the multi-process rows.
# Results -> $OUT and /tmp/keep (for later calls on the same machine).
#   RESOLUTIONS=112 CLIPS=24 bash scripts/gpu/render_bench.sh
set -uo pipefail
source scripts/gpu/env.sh
mkdir -p /tmp/keep
for res in ${RESOLUTIONS:-224 112}; do
  python3 benchmarks/render_throughput.py --device cuda --resolution $res --spp 16 --clips ${CLIPS:-40} --frames 40 \
    --procs ${PROCS:-2,4} --write --outputs ${OUTPUTS:-npy,png+exr} --write-procs ${WRITE_PROCS:-4} \
    --out "$OUT/render_throughput-cuda-$res.json" 2>&1 | grep -vE "^\s" | grep -v "^\{" | tail -16
  python3 - "$OUT/render_throughput-cuda-$res.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))["rounds"][0]
print("ceiling", r["ceiling"])
for group in ("render_only", "with_output"):
    for name, row in r.get(group, {}).items():
        print(f"{group:12s} {name:24s} {row['frames_per_s']:9.1f} frames/s  {row.get('ceiling_ratio')} of ceiling",
              row.get("outputs", ""), f"x{row['over_host_finish']} over the host finish" if "over_host_finish" in row else "")
for name, row in r["phases"].items():
    print("phases", name, row)
PY
  ok=$(python3 -c "import json; d=json.load(open('$OUT/render_throughput-cuda-$res.json')); print(str(d['rounds'][0].get('frozen_rel_error', 1) < 1e-4).lower())")
  echo "frozen exact at $res: $ok"; echo $ok > /tmp/keep/freeze_ok_$res
  if [ "$ok" = true ] && [ -z "${SKIP_FROZEN_PROCS:-}" ]; then
    python3 benchmarks/render_throughput.py --device cuda --resolution $res --spp 16 --clips ${CLIPS:-40} --frames 40 \
      --procs ${PROCS:-2,4} --procs-freeze --out "$OUT/render_throughput-cuda-$res-frozen.json" 2>&1 | grep -E "^processes" | tail -4
  fi
done
cp $OUT/*.json /tmp/keep/

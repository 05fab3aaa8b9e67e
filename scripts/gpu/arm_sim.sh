#!/usr/bin/env bash
# GPU: the arm motion at paper size through the sim stage (retries and failures are the stability check).
set -uo pipefail
source scripts/gpu/env.sh > /dev/null
RUN=${RUN:-/tmp/paper_arm}
t0=$(date +%s.%N)
python3 -m clothgap sim --preset paper --out "$RUN" --set sim.motions=arm --set sim.remeshing=${REMESHING:-uniform1} \
  --set sim.batch_size=2592 --set sim.frames=${FRAMES:-40} 2>&1 | tr '\r' '\n' | grep "done in"
t1=$(date +%s.%N)
python3 - "$RUN" "$t1" "$t0" <<'PY' | tee "$OUT/arm_sim.json"
import glob, json, sys, collections
run, t1, t0 = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
for setting in sorted(glob.glob(f"{run}/sim/*")):
    metas = [json.load(open(f)) for f in glob.glob(f"{setting}/*/meta.json")]
    failed = [json.load(open(f)) for f in glob.glob(f"{setting}/*/FAILED")]
    print(json.dumps({"setting": setting.rsplit('/', 1)[1], "seconds": round(t1 - t0, 1), "ok": len(metas),
                      "retried_ok": sum(m["substeps"] != 8 for m in metas), "failed": len(failed),
                      "failed_classes": dict(collections.Counter(f["class_index"] for f in failed))}))
PY

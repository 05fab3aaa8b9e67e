#!/usr/bin/env bash
# GPU: lrcn's training speed on a run's real data, one model alone on each GPU (issue 13's windows/s goal).
#   bash scripts/gpu/train_speed.sh RUN [SETTING]        after the run's data is rendered (more_data.sh step 1)
# Short trainings of the preset's recipe (EPOCHS, default 3; windows/s counts the epochs after the first,
# which holds torch.compile's compilation) against the same with torch.compile, with CUDA graphs
# (compile_mode=reduce-overhead), CUDA graphs at batch 64, and whole-clip windows in batches of 16; one model
# per GPU at a time (--parallel = the GPU count), so no model shares its GPU. Table: $OUT/speed-SETTING.{md,json} (windows_per_s per recipe) and
# the models' curves in $OUT/speed-SETTING.tgz. DEADLINE seconds (default 300); the same command resumes.
# Exit status: 0 with the table, 75 when it stopped for time (call again), 1 when a model failed.
set -uo pipefail
run=$1 setting=${2:-wind-uniform1}
e=${EPOCHS:-3}
source "$(dirname "$0")/gpus.sh"
# Each recipe names its compile mode: the paper preset itself trains under graphs.
recipes=${RECIPES:-"best+epochs=$e+eager best+epochs=$e+compile=true+compile_mode=default best+epochs=$e+graphs
best+epochs=$e+batch_size=64+graphs best+epochs=$e+clip_len=40+batch_size=16+eager"}
recipes=$(echo $recipes | tr ' ' ',')
python3 "$(dirname "$0")/learn_grid.py" "$run" --setting "$setting" --parallel "${PARALLEL:-$ngpu}" \
  --deadline "${DEADLINE:-300}" --job "$recipes:lrcn" --table "speed-$setting=$recipes:lrcn" 2>&1 \
  | tr '\r' '\n' | grep -vE "it/s\]|s/it\]|clip/s\]|shard/s\]"
grid_rc=${PIPESTATUS[0]}
( cd "$run" && tar czf "${OUT:-.}/speed-$setting.tgz" $(ls -d ablation/best+epochs=*/"$setting"/*/lrcn/s*/metrics.csv \
    ablation/best+epochs=*/"$setting"/*/lrcn/s*/config.json 2>/dev/null) 2>/dev/null )
python3 - "$run/eval/speed-$setting.json" <<'EOF'
import json, sys
try:
    rows = json.load(open(sys.argv[1]))["recipes"]
except OSError:
    print("no speed table yet: call again")
    sys.exit(75)
for r in rows:
    s = r["speed"][0]
    print(f"{r['recipe']:70s} {s['windows_per_s']:>8} windows/s  first epoch {s['first_epoch_seconds']} s")
EOF
rc=$?
[ "$grid_rc" = 0 ] || { echo "train_speed: a model failed (learn_grid exit $grid_rc)"; exit 1; }
exit $rc

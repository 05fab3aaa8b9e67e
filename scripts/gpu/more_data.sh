#!/usr/bin/env bash
# GPU: one setting at full size, data to Table 3 row, one command per call until it is done.
#   RUN=/tmp/wind bash scripts/gpu/more_data.sh                 (call it again after a cut-off: it goes on)
#   MOTIONS=arm RUN=/tmp/arm bash scripts/gpu/more_data.sh      arm-uniform1
#   SEQ=144 ... sequences per class (default: the preset's, 384); LEVERS="..." the lrcn recipes beside the row's
#   ROW=best+clip_len=40 ... the recipe of the Table 3 row (default `best`, the preset's recipe), the levers' reference
# 1. the setting at the paper preset (sim + render, scripts/gpu/paper_study.sh);
# 2. one training pool over the machine's GPUs (scripts/gpu/learn_grid.py): the Table 3 row (lrcn, base1,
#    base2, base3 on ROW) beside lrcn levers on the same clips, e.g.
#    best+train_fraction=0.5 (half the training sequences a class on this data's test clips: the data-size
#    lever alone) or best+seeds=1 (how much a rerun moves);
# 3. the measured-fabric set on the row's models (clothgap eval measured, held-out variant).
# Stops in time for the device's 10-minute limit (BUDGET seconds in all); every step resumes.
# DATA_ONLY=1 stops after step 1; MEASURED=0 leaves step 3 out. Exit status: 0 when everything asked for is
# done, 75 when it stopped for time (call again), 1 when a stage or a model failed (scripts/gpu/queue.sh).
set -uo pipefail
source scripts/gpu/env.sh
export RUN=${RUN:-/tmp/wind} MOTIONS=${MOTIONS:-wind}; SEQ=${SEQ:-}; BUDGET=${BUDGET:-560}
SETTING=${SETTING:-$MOTIONS-uniform1}
ROW=${ROW:-best}
LEVERS=${LEVERS-"$ROW+seeds=1"}
t0=$(date +%s); left() { echo $(( BUDGET - ($(date +%s) - t0) )); }
log=$OUT/more_data.log
# outputs are named after the data's size as the run holds it (SEQ, else the preset's): seq96, ...
data_tag() { python3 -c "import json,sys; print('seq%d' % json.load(open(sys.argv[1]))['sim']['sequences_per_class'])" \
  "$RUN/config.json" 2>/dev/null; }
source "$(dirname "$0")/gpus.sh"

# 1. data (quick when finished: every clip's DONE is checked and skipped)
if [ ! -f "$RUN/.data-done" ]; then
  for stage in sim render; do
    # render only simulations that are all finished (the split is made from them)
    [ $stage = render ] && ! tail -1 "$RUN/gpu_timings.jsonl" 2>/dev/null | grep -q '"stage": "sim", "rc": 0' && break
    [ "$(left)" -gt 90 ] && LIMIT=$(( $(left) - 30 )) SEQ=$SEQ STAGES=$stage SPP=16 bash scripts/gpu/paper_study.sh 2>&1 \
      | tee -a "$log"
  done
  tail -2 "$RUN/gpu_timings.jsonl" | grep -q '"stage": "render", "rc": 0' && touch "$RUN/.data-done"
  cp "$RUN/gpu_timings.jsonl" "$OUT/gpu_timings-${TAG:-$(data_tag)}.jsonl" 2>/dev/null
  # a stage that failed, not one cut off by its time limit (124, 137), fails the call
  tail -1 "$RUN/gpu_timings.jsonl" 2>/dev/null | grep -qvE '"rc": (0|124|137),' && {
    echo "data: a stage failed: $(tail -1 "$RUN/gpu_timings.jsonl")" | tee -a "$log"; exit 1; }
fi
[ -f "$RUN/.data-done" ] || { echo "data not finished: call again" | tee -a "$log"; exit 75; }
[ "${DATA_ONLY:-0}" = 1 ] && { echo "data done"; exit 0; }
TAG=${TAG:-$(data_tag)}

# 2. the training pool, then the tables of whatever has finished
jobs=(--job "$ROW:lrcn,base1,base2,base3")
for r in $LEVERS; do jobs+=(--job "$r:lrcn"); done
lever_list=$(echo $ROW $LEVERS | tr ' ' ',')
grid_rc=0
if [ "$(left)" -gt 60 ]; then
  python3 scripts/gpu/learn_grid.py "$RUN" --setting "$SETTING" \
      --parallel "${PARALLEL:-$((3 * ngpu))}" --deadline $(( $(left) - 45 )) "${jobs[@]}" \
      --table "models-$SETTING-$TAG=$ROW:lrcn,base1,base2,base3" --table "levers-$SETTING-$TAG=$lever_list:lrcn" \
      2>&1 | tr '\r' '\n' | grep -vE "it/s\]|s/it\]|clip/s\]|shard/s\]" | tee -a "$log"
  grid_rc=${PIPESTATUS[0]}
fi

# 3. the measured fabrics on the row's models, once they are all finished
if [ -f "$RUN/eval/models-$SETTING-$TAG.json" ] && [ ! -f "$RUN/eval/measured.json" ] && [ "$(left)" -gt 90 ]; then
  LIMIT=$(( $(left) - 15 )) bash scripts/gpu/measured.sh "$RUN" "$SETTING" "$ROW" "lrcn base1 base2 base3" \
    "measured-$SETTING-$TAG" 2>&1 | tee -a "$log"
fi
# the curves and speed of every model trained so far (finished or not), for a call that ends early
( cd "$RUN" && tar czf "$OUT/models-$TAG.tgz" $(ls -d ablation/*/*/*/*/s*/metrics.csv ablation/*/*/*/*/s*/config.json \
    ablation/*/*/*/*/s*/DONE 2>/dev/null) config.json gpu_timings.jsonl 2>/dev/null )
echo "call done in $(( $(date +%s) - t0 )) s"
[ "${grid_rc:-0}" = 0 ] || { echo "training: a model failed (learn_grid exit $grid_rc)"; exit 1; }
[ -f "$RUN/eval/models-$SETTING-$TAG.json" ] && [ -f "$RUN/eval/levers-$SETTING-$TAG.json" ] &&
  { [ "${MEASURED:-1}" = 0 ] || [ -f "$RUN/eval/measured.json" ]; } && exit 0
exit 75

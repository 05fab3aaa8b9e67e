#!/usr/bin/env bash
# GPU: one Table 3 row (a motion's uniform1 setting, the `paper` preset, all four models, seeds 0 and 1, each model
# also scored as its two seeds' ensemble) with the models' lattice regressor shared: lrcn trains its CNN, and
# base1, base2 and base3 train their readers alone on lrcn's frozen CNN (train.shared_regressor=lrcn). In the
# bottleneck recipe the class loss never reaches the CNN, so the four models train the same pixels -> lattice
# regressor: a row costs two CNN trainings instead of about seven (at 192 sequences a class a row
# wants two GPUs for one session: docs/learning.md, sixteenth and seventeenth sessions).
#   bash scripts/gpu/table3_shared.sh data RUN     simulate and render (the run is made on first use)
#   bash scripts/gpu/table3_shared.sh train RUN    lrcn seeds 0 and 1, then the readers; with OWN=1 also base1
#                                                  with its own CNN and base2 on that CNN (seed 0, recipe
#                                                  `shared_regressor=base1+seeds=0`) beside them, for `own`
#   bash scripts/gpu/table3_shared.sh lrcn RUN     lrcn seeds 0 and 1 alone (every look of LOOKS), before `looks`
#                                                  or `half`; with HALF=1 also the same lrcn on half of each
#                                                  class's training sequences (recipe train_fraction=0.5) beside
#   bash scripts/gpu/table3_shared.sh looks RUN    lrcn in LOOKS' second look against the first, seeds pooled and
#                                                  as ensembles, on validation windows (the choice) and test
#                                                  clips (pooled_recipes.py); the look validation prefers goes
#                                                  to RUN/chosen_look, the one `train` then trains readers on
#   bash scripts/gpu/table3_shared.sh half RUN     lrcn on all training sequences against half of them (HALF=1's
#                                                  models), the same way, in LOOKS' first look: what the data
#                                                  size buys
#   bash scripts/gpu/table3_shared.sh eval RUN     eval and report: RUN/eval/table3.md
#   bash scripts/gpu/table3_shared.sh own RUN      base1 and base2 of seed 0 reading lrcn's regressor against the
#                                                  same models on their own CNN (OWN=1's), paired by clip, on
#                                                  validation windows (the choice) and test clips
#                                                  (pooled_recipes.py); in the readers' look (the chosen one,
#                                                  else LOOKS' first)
# LOOKS (default paper): the render variants the run renders, comma-separated (e.g. paper,close: a look against
# the paper's, lrcn trained on each, the readers on the one validation chooses).
# RUN's name after "t3" is the motion (/tmp/t3wind: wind-uniform1). BUDGET (seconds) bounds a step; every step
# resumes when called again. Exit status: 0 done, 75 call again, 1 failed. PLAN_SETS adds settings to the run
# (a CPU dry run: sim.device=cpu, ...). Outputs go to $OUT.
set -uo pipefail
[ $# -eq 2 ] || { echo "usage: bash scripts/gpu/table3_shared.sh data|lrcn|looks|half|train|eval|own RUN" >&2; exit 2; }
step=$1 run=$2
here=$(cd "$(dirname "$0")" && pwd)
source "$here/t3run.sh"
out=${OUT:-/tmp}
budget=${BUDGET:-560}
own=shared_regressor=base1+seeds=0 half=train_fraction=0.5
export RUN=$run MOTIONS=$motion SPP=16
looks=${LOOKS:-paper}
IFS=, read -r first second _ <<< "$looks"
# The readers train as the preset does, each step replayed from a CUDA graph (train.reader_graphs), unless
# READER_GRAPHS=0 or scripts/gpu/plans/reader-graphs.plan's check did not pass on this machine (its mark
# READER_GRAPHS_OFF, which the check writes first and removes when the graphs hold): then eagerly.
reader_graphs=
if [ "${READER_GRAPHS:-1}" = 0 ] || [ -f "${READER_GRAPHS_OFF:-/tmp/reader-graphs.off}" ]; then
  reader_graphs="--set train.reader_graphs=false"
fi
export EXTRA="--set train.seeds=0,1 --set eval.seed_ensemble=true --set eval.measured_sequences=0 --set train.shared_regressor=lrcn --set render.variants=$looks $reader_graphs ${PLAN_SETS:-}"
source "$here/gpus.sh"
# `train` after `looks`: the readers of the chosen look only
chosen=$(cat "$run/chosen_look" 2>/dev/null)
export TRAIN_ARGS="--parallel $((4 * ngpu))${chosen:+ --variant $chosen}"
# the look the readers train on: the chosen one, else the first (where `own` checks them and `beside` trains)
row_look=${chosen:-$first}

# beside NAME RECIPES:MODELS LOOK: learn_grid trains those recipes in the background on LOOK, beside the step's own
# training, once that look's frame cache is built (else both would pack the same frames), within what the wait left
# of the step's budget; its log and exit status go to $out/NAME.{log,rc}. Sets beside_pid and beside_look.
beside_pid= beside_look=
beside() {
  beside_look=$3
  ( for _ in $(seq 120); do ls "$run"/cache/"$beside_look"/"$setting"/*.json > /dev/null 2>&1 && break; sleep 2; done
    left=$((budget - SECONDS))
    if [ $left -gt 90 ]; then
      timeout $((left - 20)) python3 "$here/learn_grid.py" "$run" --setting "$setting" --variant "$beside_look" \
        --parallel 2 --deadline $((left - 60)) --job "$2" > "$out/$1.log" 2>&1
      echo $? > "$out/$1.rc"
    else
      echo 124 > "$out/$1.rc"
    fi ) &
  beside_pid=$!
}

# beside_done NAME MODELS RECIPE SEEDS: waits for `beside` (in this shell: the job is its child), then turns rc from
# 0 into 75 when one of its models is unfinished for time; a failure of theirs is left to the step that needs them
beside_done() {
  local model seed
  wait "$beside_pid"
  grep -v UserWarning "$out/$1.log" 2>/dev/null | grep -e 'training call' -e Error
  case $(cat "$out/$1.rc" 2>/dev/null) in
    0|124|137) ;;
    *) echo "the models beside failed ($out/$1.log): the step that reads them will say so"; return ;;
  esac
  for model in ${2//,/ }; do
    for seed in $4; do
      [ -f "$run/ablation/$3/$setting/$beside_look/$model/s$seed/DONE" ] || { [ "$rc" = 0 ] && rc=75; }
    done
  done
}

# scored RECIPE LOOK: the recipe's two lrcn scored on their test clips (learn_grid's table writes each model's
# test_predictions.csv), once
scored() {
  local name=lrcn-$setting-$2-${1//=/}      # (a table's name holds no "=")
  [ -f "$run/eval/$name.json" ] && return 0
  python3 "$here/learn_grid.py" "$run" --setting "$setting" --variant "$2" --table "$name=$1:lrcn" \
    > "$out/$name-table.log" 2>&1 || { grep -v UserWarning "$out/$name-table.log" | tail -3; return 1; }
  [ -f "$run/eval/$name.json" ] || { grep -v UserWarning "$out/$name-table.log" | tail -3; return 1; }
}

# compared NAME A B: lrcn seeds 0 and 1 of side A (LOOK:RECIPE) against side B, pooled and as ensembles, on
# validation windows (the choice) and test clips: $out/NAME-{val,own}[-ensemble].json
compared() {
  local scored_on ens failed=0
  for scored_on in val own; do
    for ens in "" "--a-ensemble --b-ensemble"; do
      echo "lrcn, $2 against $3, $scored_on${ens:+, ensembles}:"
      python3 "$here/../pooled_recipes.py" "$run" --setting "$setting" --look $scored_on $ens \
        --a "$2@0,${2#*:}@1" --b "$3@0,${3#*:}@1" > "$out/$1-$scored_on${ens:+-ensemble}.json" || failed=1
    done
  done
  return $failed
}

# predictions NAME: every lrcn's test and validation predictions and curves under ablation/, as $out/NAME.tgz (a
# failure to pack is said, not the step's: its results are in the run and the JSONs beside)
predictions() {
  local parent base
  parent=$(dirname "$run") base=$(basename "$run")
  ( cd "$parent" && tar czf "$out/$1.tgz" $(ls "$base"/chosen_look 2>/dev/null) \
      $(ls -d "$base"/ablation/*/*/*/lrcn/s*/{test,val}_predictions.csv "$base"/ablation/*/*/*/lrcn/s*/metrics.csv \
        2>/dev/null) ) || echo "predictions: $out/$1.tgz not packed"
}

case $step in
  data) STAGES="sim render" bash "$here/paper_study.sh" ;;
  train)
    [ "${OWN:-0}" = 1 ] && beside own-cnn "$own:base1,base2" "$row_look"
    STAGES=train bash "$here/paper_study.sh"
    rc=$?
    # the own-CNN models are the `own` step's check, not the row: their failure fails that step, not this one
    [ -n "$beside_pid" ] && beside_done own-cnn base1,base2 "$own" 0
    exit $rc ;;
  lrcn)
    # (before `looks` chooses: the first look, as `half` reads them)
    [ "${HALF:-0}" = 1 ] && beside half "$half:lrcn" "$first"
    TRAIN_ARGS="--parallel $((4 * ngpu)) --model lrcn" STAGES=train bash "$here/paper_study.sh"
    rc=$?
    [ -n "$beside_pid" ] && beside_done half lrcn "$half" "0 1"
    exit $rc ;;
  looks)
    [ -n "${second:-}" ] || { echo "looks: LOOKS names one look ($looks): nothing to compare" >&2; exit 1; }
    # each look's two lrcn as the recipe `baseline` (the run's own: hard links, nothing retrained)
    for v in "$first" "$second"; do
      for seed in 0 1; do link_trained lrcn "$seed" baseline "$v" || exit 1; done
      scored baseline "$v" || exit 1
    done
    compared "looks-$motion-$second" "$second:baseline" "$first:baseline" || exit 1
    # validation windows choose, seeds pooled: the look whose lrcn read more of them
    python3 - "$out/looks-$motion-$second-val.json" "$second" "$first" > "$run/chosen_look.partial" <<'PY' || exit 1
import json, sys
result, look, ref = json.load(open(sys.argv[1])), sys.argv[2], sys.argv[3]
print(look if result["acc_a_minus_b"] > 0 else ref)
PY
    mv "$run/chosen_look.partial" "$run/chosen_look"
    echo "validation chooses $(cat "$run/chosen_look") for the readers"
    predictions "looks-$motion" ;;
  half)
    for seed in 0 1; do
      [ -f "$run/ablation/$half/$setting/$first/lrcn/s$seed/DONE" ] || { echo "$half lrcn s$seed is not trained (HALF=1 lrcn)" >&2; exit 1; }
      link_trained lrcn "$seed" baseline "$first" || exit 1
    done
    scored baseline "$first" && scored "$half" "$first" || exit 1
    compared "half-$motion" "$first:baseline" "$first:$half" || exit 1
    predictions "half-$motion" ;;
  eval) STAGES="eval report" bash "$here/paper_study.sh" && head -20 "$run/eval/table3.md" ;;
  own)
    # the row's seed-0 readers as the `seeds=0` recipe (the run's recipe with seed 0 alone: hard links, nothing
    # retrained), then both recipes scored on the test clips (learn_grid's table: each model's test predictions)
    # and compared
    ref=seeds=0
    for model in base1 base2; do
      [ -f "$run/ablation/$own/$setting/$row_look/$model/s0/DONE" ] || { echo "$own $model is not trained" >&2; exit 1; }
      link_trained "$model" 0 "$ref" "$row_look" || exit 1
    done
    python3 "$here/learn_grid.py" "$run" --setting "$setting" --variant "$row_look" \
      --table "own-cnn-$setting=$ref,$own:base1,base2" > "$out/own-cnn-table.log" 2>&1 || exit 1
    grep -v UserWarning "$out/own-cnn-table.log" | grep -e '|' -e Error
    [ -f "$run/eval/own-cnn-$setting.json" ] || exit 1
    failed=0
    for model in base1 base2; do
      for look in val own; do
        echo "$model on lrcn's regressor against its own CNN, seed 0, $look:"
        python3 "$here/../pooled_recipes.py" "$run" --setting "$setting" --model "$model" --look "$look" \
          --a "$row_look:$ref@0" --b "$row_look:$own@0" > "$out/own-$motion-$model-$look.json" || failed=1
      done
    done
    [ $failed = 0 ] ;;
  *) echo "usage: bash scripts/gpu/table3_shared.sh data|lrcn|looks|half|train|eval|own RUN" >&2; exit 2 ;;
esac

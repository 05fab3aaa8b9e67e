#!/usr/bin/env bash
# GPU: a motion's uniform1 at 192 sequences a class, lrcn seeds 0 and 1 on all its training sequences against the
# same seeds on half of them (train.train_fraction=0.5: the 96-a-class training set), the same validation and test
# clips: the data-size lever of arm-data192.plan (wind's is table3_shared.sh's `half` step: wind-t3-192.plan).
#   bash scripts/gpu/data192.sh data MOTION       simulate and render /tmp/MOTION192 (the run is made on first use)
#   bash scripts/gpu/data192.sh train MOTION      the four lrcn (four at a time over the lane's GPUs) and their table
#   bash scripts/gpu/data192.sh compare MOTION    192 against 96 on validation windows (the choice) and test clips,
#                                                 seeds pooled and as ensembles (pooled_recipes.py), and a tarball
# BUDGET (seconds) bounds `train`, which resumes when called again; N replaces 192 (a CPU dry run). Exit status: 0
# done, 75 call again, 1 failed. PLAN_SETS adds settings to the run. Outputs go to $OUT.
set -uo pipefail
[ $# -eq 2 ] || { echo "usage: bash scripts/gpu/data192.sh data|train|compare MOTION" >&2; exit 2; }
step=$1 motion=$2
name=${motion}192 setting=$motion-uniform1
run=/tmp/$name tag=${motion:0:1}192 out=${OUT:-/tmp} budget=${BUDGET:-560}
here=$(cd "$(dirname "$0")" && pwd)
full=baseline,baseline+seeds=1 half=train_fraction=0.5,train_fraction=0.5+seeds=1
case $step in
  data)
    RUN=$run MOTIONS=$motion SEQ=${N:-192} SPP=16 STAGES="sim render" \
      EXTRA="--set eval.measured_sequences=0 --set train.models=lrcn ${PLAN_SETS:-}" bash "$here/paper_study.sh" ;;
  train)
    timeout $((budget - 20)) python3 "$here/learn_grid.py" "$run" --setting "$setting" --variant paper --parallel 4 \
      --deadline $((budget - 90)) --job "$full,$half:lrcn" --table "$name=$half,$full:lrcn" > "/tmp/$name.log" 2>&1
    rc=$?
    grep -v UserWarning "/tmp/$name.log" | grep -e '|' -e 'training call' -e Error
    cp "/tmp/$name.log" "$out/"
    case $rc in 0|124|137) ;; *) exit 1 ;; esac
    [ -f "$run/eval/$name.json" ] || exit 75 ;;
  compare)
    failed=0
    for look in val own; do
      for ens in "" "--a-ensemble --b-ensemble"; do
        echo "192 against 96 a class, $look ${ens:+ensembles}:"
        python3 "$here/../pooled_recipes.py" "$run" --setting "$setting" --look $look $ens \
          --a paper:baseline@0,baseline+seeds=1@1 --b paper:train_fraction=0.5@0,train_fraction=0.5+seeds=1@1 \
          > "$out/$tag-$look${ens:+-ensemble}.json" || failed=1
      done
    done
    cd /tmp && tar czf "$out/$name.tgz" $name/config.json $name/gpu_timings.jsonl $name/eval/*.json $name/eval/*.md \
      $(ls -d $name/ablation/*/*/*/lrcn/s*/test_predictions*.csv $name/ablation/*/*/*/lrcn/s*/val_predictions.csv \
         $name/ablation/*/*/*/lrcn/s*/metrics.csv)
    [ $failed = 0 ] ;;
  *) echo "data192.sh: unknown step $step (data, train or compare)" >&2; exit 2 ;;
esac

#!/usr/bin/env bash
# GPU: readers on a shared regressor against the same models with their own CNN (train.shared_regressor), on a run
# whose four models are trained with seeds 0 and 1 (a Table 3 run: table3-ensemble-{wind,arm}.plan).
#   bash scripts/gpu/shared_regressor.sh link RUN       the run's models as the `baseline` recipe, its lrcn as the
#                                                       `shared_regressor=lrcn` recipe's (hard links, nothing retrained)
#   bash scripts/gpu/shared_regressor.sh train RUN      base1, base2 and base3 of seeds 0 and 1 on lrcn's shapes, and
#                                                       base2 again with READER_EPOCHS (default 240) epochs, then the
#                                                       tables (RUN/eval/shared-regressor-SETTING.*, and
#                                                       shared-reader-epochs-SETTING.*)
#   bash scripts/gpu/shared_regressor.sh compare RUN    each model's two seeds against its own-CNN seeds, and the long
#                                                       readers against lrcn itself, pooled per clip, on validation
#                                                       windows (the choice) and test clips
# The setting is RUN's name after "t3" (t3wind: wind-uniform1); the variant is `paper`. BUDGET (seconds) bounds
# `train`, which resumes when called again (exit status 75 until its table exists). Outputs go to $OUT.
set -uo pipefail
step=$1 run=$2
source "$(dirname "$0")/t3run.sh"
out=${OUT:-/tmp}
budget=${BUDGET:-560}
long=shared_regressor=lrcn+reader_epochs=${READER_EPOCHS:-240}
# "model seed recipe" of every link: the run's four models as the reference, its lrcn as each shared recipe's regressor
links() {
  for model in lrcn base1 base2 base3; do
    for s in 0 1; do
      for recipe in baseline shared_regressor=lrcn $long; do
        { [ "$recipe" = baseline ] || [ "$model" = lrcn ]; } && echo "$model $s $recipe"
      done
    done
  done
}
case $step in
  link)
    while read -r model s recipe; do
      link_trained "$model" "$s" "$recipe" || exit 1
    done < <(links) ;;
  train)
    # Only readers train here: every model of the reference and the regressor must be linked first (a missing
    # lrcn would otherwise be trained from scratch under the recipe, and a missing reference never tabled).
    while read -r model s recipe; do
      [ -f "$run/ablation/$recipe/$setting/paper/$model/s$s/DONE" ] \
        || { echo "$recipe $model s$s is not linked: run the link step first" >&2; exit 1; }
    done < <(links)
    timeout $((budget - 20)) python3 "$(dirname "$0")/learn_grid.py" "$run" --setting "$setting" --variant paper \
      --parallel 8 --deadline $((budget - 90)) --job "$long:base2" --job shared_regressor=lrcn:base1,base2,base3 \
      --table "shared-regressor-$setting=baseline,shared_regressor=lrcn:lrcn,base1,base2,base3" \
      --table "shared-reader-epochs-$setting=shared_regressor=lrcn,$long:base2" > "$out/shared-regressor.log" 2>&1
    rc=$?
    grep -v UserWarning "$out/shared-regressor.log" | grep -e '|' -e 'training call' -e Error
    case $rc in 0|124|137) ;; *) exit 1 ;; esac
    [ -f "$run/eval/shared-regressor-$setting.json" ] && [ -f "$run/eval/shared-reader-epochs-$setting.json" ] || exit 75
    cp "$run/eval/shared-regressor-$setting".* "$run/eval/shared-reader-epochs-$setting".* "$out/" ;;
  compare)
    failed=0
    for model in base1 base2 base3; do
      for look in val own; do
        echo "$model, $look:"
        python3 "$(dirname "$0")/../pooled_recipes.py" "$run" --setting "$setting" --model "$model" --look "$look" \
          --a paper:shared_regressor=lrcn@0,shared_regressor=lrcn@1 --b paper:baseline@0,baseline@1 \
          > "$out/shared-$model-$look.json" || failed=1
      done
    done
    for look in val own; do
      echo "base2 reading lrcn's shapes for ${READER_EPOCHS:-240} epochs against lrcn itself, $look:"
      python3 "$(dirname "$0")/../pooled_recipes.py" "$run" --setting "$setting" --model base2 --b-model lrcn \
        --look "$look" --a "paper:$long@0,$long@1" --b paper:baseline@0,baseline@1 > "$out/long-reader-$look.json" \
        || failed=1
    done
    [ $failed = 0 ] ;;
  *) echo "usage: bash scripts/gpu/shared_regressor.sh link|train|compare RUN" >&2; exit 2 ;;
esac

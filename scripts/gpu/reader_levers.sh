#!/usr/bin/env bash
# GPU: levers for the readers of a finished shared regressor, on a Table 3 run made by table3_shared.sh (its
# lrcn of seeds 0 and 1 is the regressor, its base2 the reference). Only readers train, a few minutes in all.
#   bash scripts/gpu/reader_levers.sh train RUN LEVER [LEVER...]   base2 of seeds 0 and 1 under each lever
#                                                                  (an ablation recipe, e.g. bottleneck_noise=0.4)
#   bash scripts/gpu/reader_levers.sh compare RUN LEVER [LEVER...] each lever against the run's base2, and
#                                                                  against its lrcn, on validation windows (the
#                                                                  choice) and test clips (pooled_recipes.py)
# The run's lrcn is linked into each lever's folder as its regressor (hard links, nothing retrained: the reader's
# config.json records the regressor's sha256, so a reader never mixes two), its lrcn and base2 as the `baseline`
# recipe.
# RUN's name after "t3" is the motion (/tmp/t3wind: wind-uniform1). BUDGET (seconds) bounds `train`, which
# resumes when called again. Exit status: 0 done, 75 call again, 1 failed. Outputs go to $OUT.
set -uo pipefail
[ $# -ge 3 ] || { echo "usage: bash scripts/gpu/reader_levers.sh train|compare RUN LEVER [LEVER...]" >&2; exit 2; }
step=$1 run=$2; shift 2
levers=("$@")
here=$(cd "$(dirname "$0")" && pwd)
source "$here/t3run.sh"
out=${OUT:-/tmp}
budget=${BUDGET:-560}
case $step in
  train)
    for s in 0 1; do
      link_trained base2 $s baseline && link_trained lrcn $s baseline || exit 1
      for lever in "${levers[@]}"; do link_trained lrcn $s "$lever" || exit 1; done
    done
    recipes=$(IFS=,; echo "${levers[*]}")
    timeout $((budget - 20)) python3 "$here/learn_grid.py" "$run" --setting "$setting" --variant paper \
      --parallel 8 --deadline $((budget - 90)) --job "$recipes:base2" \
      --table "reader-levers-$setting=baseline,$recipes:lrcn,base2" > "$out/reader-levers.log" 2>&1
    rc=$?
    grep -v UserWarning "$out/reader-levers.log" | grep -e '|' -e 'training call' -e Error
    case $rc in 0|124|137) ;; *) exit 1 ;; esac
    [ -f "$run/eval/reader-levers-$setting.json" ] || exit 75 ;;
  compare)
    failed=0
    for lever in "${levers[@]}"; do
      for look in val own; do
        echo "base2 under $lever against the row's base2, $look:"
        python3 "$here/../pooled_recipes.py" "$run" --setting "$setting" --model base2 --look "$look" \
          --a "paper:$lever@0,$lever@1" --b paper:baseline@0,baseline@1 > "$out/reader-$lever-$look.json" || failed=1
        echo "base2 under $lever against the row's lrcn, $look:"
        python3 "$here/../pooled_recipes.py" "$run" --setting "$setting" --model base2 --b-model lrcn --look "$look" \
          --a "paper:$lever@0,$lever@1" --b paper:baseline@0,baseline@1 > "$out/reader-$lever-lrcn-$look.json" \
          || failed=1
      done
    done
    [ $failed = 0 ] ;;
  *) echo "usage: bash scripts/gpu/reader_levers.sh train|compare RUN LEVER [LEVER...]" >&2; exit 2 ;;
esac

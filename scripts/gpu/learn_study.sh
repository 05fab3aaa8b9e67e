#!/usr/bin/env bash
# GPU: training recipes compared on one rendered setting (clothgap eval ablation), each model in its own
# process so that a failure costs one row, stopping before the device's 10-minute limit.
#   RECIPES="baseline best augment+best" MODELS=lrcn bash scripts/gpu/learn_study.sh
#   RECIPES=auto MODELS="base1 base2 base3" ...   the recipe with the best lrcn validation accuracy so far
#                    (of $RUN/eval/ablation-<setting>-<variant>.json, NAME's default; rows with seeds= or
#                    train_fraction= are measurements, not candidates)
#   PARALLEL=4 ...   four models at a time (windows/s then is not a solo figure), round robin over the GPUs
#   MEASURED=1 ...   then the measured-fabric set (clothgap eval measured, held-out variant) on this call's
#                    models of the first (or chosen) recipe, scored where they are (scripts/gpu/measured.sh)
# The data comes first: STAGES="sim render" SPP=16 RUN=/tmp/paper_study bash scripts/gpu/paper_study.sh
# Every recipe resumes epoch by epoch, so a call cut short loses at most one epoch: call again.
#   RECIPES="best best+seeds=1 best+train_fraction=0.5"   another training seed (how much a rerun moves),
#                    half of each class's training sequences (the data-size learning curve)
# Writes $OUT/ablation-<setting>-<variant>.{json,md} (every finished recipe) and $OUT/learn_study.log.
set -uo pipefail
source scripts/gpu/env.sh
RUN=${RUN:-/tmp/paper_study}; SETTING=${SETTING:-wind-uniform1}; VARIANT=${VARIANT:-paper}
MODELS=${MODELS:-lrcn}; DEADLINE=${DEADLINE:-520}; FIRST=${FIRST:-baseline}
# the combined table of this call's models (lrcn's recipes: the table RECIPES=auto chooses from)
[ "$MODELS" = lrcn ] && NAME=${NAME:-ablation-$SETTING-$VARIANT} || NAME=${NAME:-models-$SETTING-$VARIANT}
ABL=(python3 -m clothgap eval ablation "$RUN" --setting "$SETTING" --variant "$VARIANT")
t0=$(date +%s)
finished() {  # recipes whose every model is DONE, FIRST first
  python3 - "$RUN" "$SETTING" "$VARIANT" "$FIRST" "$@" <<'PY'
import sys, pathlib
run, setting, variant, first, *models = sys.argv[1:]
root = pathlib.Path(run) / "ablation"
names = sorted(p.name for p in root.iterdir()) if root.is_dir() else []
done = [n for n in names if all(any((root / n / setting / variant / m).glob("s*/DONE")) for m in models)]
print(" ".join(([first] if first in done else []) + [n for n in done if n != first]))
PY
}
if [ "$RECIPES" = auto ]; then
  RECIPES=$(python3 - "$RUN/eval/ablation-$SETTING-$VARIANT.json" <<'PY'
import json, sys
# measurements rather than recipes (another seed, less data) are not candidates; epochs are a lever
rows = [r for r in json.load(open(sys.argv[1]))["recipes"] if r["model"] == "lrcn"
        and not any(k in r["recipe"] for k in ("seeds=", "train_fraction="))]
if not rows:
    sys.exit(f"RECIPES=auto: {sys.argv[1]} has no lrcn recipe to choose from; run lrcn recipes first")
def val(r):   # validation accuracy of the kept epoch: recipes are chosen on validation clips, never test
    kept = r["speed"][0]["kept_epoch"]
    return next(iter(r["curves"].values()))[kept]["val_acc"]
print(max(rows, key=val)["recipe"])
PY
)
  [ -n "$RECIPES" ] || exit 1
  echo "recipe chosen on validation accuracy: $RECIPES"
  echo "$RECIPES" > "$RUN/eval/chosen-recipe.txt"
fi
# One training pool for every recipe's models (scripts/gpu/learn_grid.py: PARALLEL at a time over the machine's
# GPUs, the shared caches built first, stopped at the deadline; the same command resumes every model).
left=$(( DEADLINE - ($(date +%s) - t0) ))
if [ $left -ge 30 ]; then
  python3 scripts/gpu/learn_grid.py "$RUN" --setting "$SETTING" --variant "$VARIANT" --parallel "${PARALLEL:-1}" \
    --deadline "$left" --job "$(echo $RECIPES | tr ' ' ','):$(echo $MODELS | tr ' ' ',')" 2>&1 \
    | tr '\r' '\n' | grep -vE "it/s\]|s/it\]|clip/s\]|shard/s\]"
else
  echo "deadline: no training started"
fi
done_recipes=$(finished $MODELS)
if [ -n "$done_recipes" ]; then
  rargs=(); for r in $done_recipes; do rargs+=(--recipe "$r"); done
  margs=(); for m in $MODELS; do margs+=(--model "$m"); done
  "${ABL[@]}" "${rargs[@]}" "${margs[@]}" --name "$NAME" 2>&1 | tail -2
  cp "$RUN/eval/$NAME.json" "$RUN/eval/$NAME.md" "$OUT"/ 2>/dev/null
  cat "$RUN/eval/$NAME.md"
fi
if [ "${MEASURED:-0}" = 1 ]; then
  VARIANT=$VARIANT bash scripts/gpu/measured.sh "$RUN" "$SETTING" "${RECIPES%% *}" "$MODELS"
fi
nvidia-smi --query-gpu=memory.used --format=csv,noheader

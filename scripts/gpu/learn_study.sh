#!/usr/bin/env bash
# GPU: training recipes compared on one rendered setting (clothgap eval ablation), one recipe per
# process so that a failure costs one row, stopping before the device's 10-minute limit.
#   RECIPES="baseline best augment+best" MODELS=lrcn bash scripts/gpu/learn_study.sh
#   RECIPES=auto MODELS="base1 base2 base3" ...   the recipe with the best lrcn validation accuracy so far
#                    (of $RUN/eval/ablation-<setting>-<variant>.json, NAME's default; rows with seeds= or
#                    train_fraction= are measurements, not candidates)
#   PARALLEL=4 ...   four recipes at a time (windows/s then is not a solo figure); on a machine of several
#                    GPUs each recipe goes to the GPU running the fewest (CUDA_VISIBLE_DEVICES)
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
NAME=${NAME:-ablation-$SETTING-$VARIANT}    # the combined table of this call's models
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
def val(r):   # validation accuracy of the kept epoch: recipes are chosen on validation clips, never test
    kept = r["speed"][0]["kept_epoch"]
    return next(iter(r["curves"].values()))[kept]["val_acc"]
print(max(rows, key=val)["recipe"])
PY
)
  echo "recipe chosen on validation accuracy: $RECIPES"
  echo "$RECIPES" > "$RUN/eval/chosen-recipe.txt"
fi
margs=(); for m in $MODELS; do margs+=(--model "$m"); done
if [ "${PARALLEL:-1}" -gt 1 ]; then
  # Recipes share the GPU, PARALLEL at a time (a model at batch 64 leaves most of an H100 idle).
  # The split, frame caches (at each recipe's image size) and lattices are built once first
  # (learn.stage.prepare_shared_inputs), so that the processes only read them.
  python3 - "$RUN" "$SETTING" "$VARIANT" $RECIPES <<'PY'
import sys
import clothgap.config  # noqa: F401  (registers the study config that Run.open reads)
from clothgap.runs import Run
from eval.ablation import ablation_grid, recipe_config
from learn.stage import prepare_shared_inputs
run, setting, variant, recipes = Run.open(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4:]
grid = ablation_grid(run, setting, variant, recipes, ["lrcn"])
prepare_shared_inputs(run, [e[:4] for e in grid], False, configs=[recipe_config(run.config, e[4]) for e in grid])
print(f"caches ready for {len(recipes)} recipe(s)")
PY
  tag() { echo "recipe-$(echo "$1" | tr '=+/' '-_-')"; }     # a recipe's log and table name
  read -ra gpus <<< "$(nvidia-smi --query-gpu=index --format=csv,noheader 2>/dev/null | tr '\n' ' ')"
  [ ${#gpus[@]} -gt 0 ] || gpus=("${CUDA_VISIBLE_DEVICES:-0}")
  declare -A gpu_of=()                                        # pid of a running recipe -> its GPU
  least_busy_gpu() {
    local best="${gpus[0]}" best_n=1000000 g n p
    for g in "${gpus[@]}"; do
      n=0; for p in "${!gpu_of[@]}"; do [ "${gpu_of[$p]}" = "$g" ] && n=$((n + 1)); done
      [ $n -lt $best_n ] && { best=$g; best_n=$n; }
    done
    echo "$best"
  }
  forget_finished() { local p; for p in "${!gpu_of[@]}"; do kill -0 "$p" 2>/dev/null || unset "gpu_of[$p]"; done; }
  for r in $RECIPES; do
    left=$(( DEADLINE - ($(date +%s) - t0) ))
    [ $left -lt 30 ] && { echo "deadline: recipe $r and later not started"; break; }
    gpu=$(least_busy_gpu)
    echo "== $r ($MODELS), $left s left, in parallel on GPU $gpu"
    log="$RUN/eval/$(tag "$r").log"; mkdir -p "$RUN/eval"
    ( export CUDA_VISIBLE_DEVICES=$gpu
      timeout $(( left + 40 )) "${ABL[@]}" --recipe "$r" "${margs[@]}" --name "$(tag "$r")" \
        2>&1 | tr '\r' '\n' | grep -vE "it/s\]|s/it\]|clip/s\]" > "$log"; echo "== $r exit ${PIPESTATUS[0]}" >> "$log" ) &
    gpu_of[$!]=$gpu
    if [ ${#gpu_of[@]} -ge "$PARALLEL" ]; then wait -n; forget_finished; fi
  done
  wait
  for r in $RECIPES; do tail -3 "$RUN/eval/$(tag "$r").log" 2>/dev/null; done
else
  for r in $RECIPES; do
    left=$(( DEADLINE - ($(date +%s) - t0) ))
    [ $left -lt 30 ] && { echo "deadline: recipe $r and later not started"; break; }
    echo "== $r ($MODELS), $left s left"
    timeout $(( left + 40 )) "${ABL[@]}" --recipe "$r" "${margs[@]}" --name "last-recipe" 2>&1 | tr '\r' '\n' \
      | grep -vE "it/s\]|s/it\]|clip/s\]" | tail -5
  done
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

#!/usr/bin/env bash
# GPU: the measured-fabric set (clothgap eval measured, held-out variant) on one ablation recipe's models.
#   bash scripts/gpu/measured.sh RUN SETTING RECIPE "MODELS" [NAME]
# The recipe's finished models (RUN/ablation/RECIPE/SETTING/VARIANT/<model>/s0, VARIANT default paper) are scored
# where they are (clothgap eval measured --model), so the run's own train/ stays the run's; the tables go to
# $OUT/NAME.{md,json} (NAME default measured). SEQUENCES per fabric (default 4); LIMIT seconds bounds the call.
set -uo pipefail
run=$1 setting=$2 recipe=$3 models=$4 name=${5:-measured} variant=${VARIANT:-paper}
args=()
for m in $models; do
  src="$run/ablation/$recipe/$setting/$variant/$m/s0"
  if [ -f "$src/DONE" ]; then args+=(--model "$src"); else echo "measured: $src is not finished, left out"; fi
done
[ ${#args[@]} -gt 0 ] || { echo "measured: no finished model of recipe $recipe"; exit 0; }
echo "== measured fabrics on recipe $recipe"
${LIMIT:+timeout -k 10 "$LIMIT"} python3 -m clothgap eval measured "$run" "${args[@]}" --sequences "${SEQUENCES:-4}" 2>&1 \
  | tr '\r' '\n' | grep -vE "it/s\]|s/it\]|clip/s\]" | tail -3
cp "$run/eval/measured.md" "$OUT/$name.md" 2>/dev/null
cp "$run/eval/measured.json" "$OUT/$name.json" 2>/dev/null
head -40 "$run/eval/measured.md" 2>/dev/null

#!/usr/bin/env bash
# GPU: the measured-fabric set (clothgap eval measured, held-out variant) on one ablation recipe's models.
#   bash scripts/gpu/measured.sh RUN SETTING RECIPE "MODELS" [NAME]
# The recipe's finished models (RUN/ablation/RECIPE/SETTING/VARIANT/<model>, VARIANT default paper) become the
# run's train/ models, which eval measured reads; the tables go to $OUT/NAME.{md,json} (NAME default measured).
# SEQUENCES per fabric (default 4); LIMIT seconds (optional) bounds the call.
set -uo pipefail
run=$1 setting=$2 recipe=$3 models=$4 name=${5:-measured} variant=${VARIANT:-paper}
mkdir -p "$run/train/$setting/$variant"
for m in $models; do
  src="$run/ablation/$recipe/$setting/$variant/$m"
  [ -f "$src/s0/DONE" ] && rm -rf "$run/train/$setting/$variant/$m" && cp -r "$src" "$run/train/$setting/$variant/$m"
done
echo "== measured fabrics on recipe $recipe"
${LIMIT:+timeout -k 10 "$LIMIT"} python3 -m clothgap eval measured "$run" --sequences "${SEQUENCES:-4}" 2>&1 \
  | tr '\r' '\n' | grep -vE "it/s\]|s/it\]|clip/s\]" | tail -3
cp "$run/eval/measured.md" "$OUT/$name.md" 2>/dev/null
cp "$run/eval/measured.json" "$OUT/$name.json" 2>/dev/null
head -40 "$run/eval/measured.md" 2>/dev/null

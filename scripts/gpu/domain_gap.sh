#!/usr/bin/env bash
# GPU: the domain-gap study (issue 15) on one setting at the paper preset: one simulation rendered under
# `paper` and variants that each change one render axis, one lrcn per variant (the preset's recipe), every
# model tested on every variant (paired test clips), the measured fabrics. paper_study.sh runs the stages
# (resumable, LIMIT or BUDGET seconds, $OUT/paper_study.tgz; exit 0 done, 75 call again, 1 failed); this only
# names the study's settings:
#   STAGES="sim render" bash scripts/gpu/domain_gap.sh          then STAGES=train, then STAGES="eval report"
# or the whole study through scripts/gpu/queue.sh scripts/gpu/plans/domain-gap-wind.plan.
# N sequences per class (default 24 on a machine of several GPUs, else 12); VARIANTS comma-separated, the
# training variants, each changing one axis of `paper` (texture, two BSDFs, lighting, background, tone curve,
# camera, motion blur); TEST_VARIANTS rendered for testing only (`clothgap render --test-variant`; default
# heldout: lighting, tone curve and camera changed at once, a look no model trains on).
# MOTIONS (default wind). One lrcn per variant, all at once (TRAIN_ARGS). The sim stage's material analyses
# are left out (eval.sim_analysis): they are the same for every variant and the paper study measures them.
# On two H100s the render of one setting's 5,184 clips took 202-270 s, so N=24 (1,296 clips) renders the ten
# variants in ~10 min (motion blur renders four instants a frame).
set -uo pipefail
ngpu=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true)
N=${N:-$([ "${ngpu:-0}" -ge 2 ] && echo 24 || echo 12)}
VARIANTS=${VARIANTS:-paper,grid,diffuse,fabric-table,lighting-random,room,filmic,camera-noise,motion-blur}
TEST_VARIANTS=${TEST_VARIANTS-heldout}
# COMBINED=NAME adds a variant of the user's ($CLOTHGAP_VARIANTS_DIR, e.g. scripts/combined_variant.py select's)
# to the run: rendered, trained and tested beside the others, which are reused.
[ -n "${COMBINED:-}" ] && VARIANTS="$VARIANTS,$COMBINED" && RUN_SETS="--set render.variants=$VARIANTS ${RUN_SETS:-}"
nvariants=$(echo "$VARIANTS" | tr ',' '\n' | grep -c .)
render_args="--executor process --gpus-per-worker 1"; [ "${ngpu:-0}" -ge 2 ] || render_args=""
for v in ${TEST_VARIANTS//,/ }; do render_args+=" --test-variant $v"; done
RUN=${RUN:-/tmp/gap} EXTRA="--set sim.sequences_per_class=$N --set sim.batch_size=$((N * 54))
  --set render.variants=$VARIANTS --set train.models=lrcn --set eval.sim_analysis= ${EXTRA:-}" SPP=${SPP:-16} \
  TRAIN_ARGS=${TRAIN_ARGS:-"--parallel $nvariants"} RENDER_ARGS=${RENDER_ARGS:-$render_args} RUN_SETS=${RUN_SETS:-} \
  exec bash scripts/gpu/paper_study.sh

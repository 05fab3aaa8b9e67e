#!/usr/bin/env bash
# GPU: the domain-gap study (issue 15) on one setting at the paper preset: one simulation rendered under
# `paper` and variants that each change one render axis, one lrcn per variant (the preset's recipe), every
# model tested on every variant (paired test clips), the measured fabrics. paper_study.sh runs the stages
# (resumable, LIMIT or BUDGET seconds, $OUT/paper_study.tgz and paper_study-report.tgz; exit 0 done, 75 call
# again, 1 failed); this only names the study's settings:
#   STAGES="sim render" bash scripts/gpu/domain_gap.sh          then STAGES=train, then STAGES="eval report"
# or the whole study through scripts/gpu/queue.sh scripts/gpu/plans/domain-gap-wind.plan. STAGES=check first
# renders two tiny clips under each variant and keeps those that rendered (below).
# N sequences per class (default 24 on a machine of several GPUs, else 12); VARIANTS comma-separated, the
# training variants, each changing one axis of `paper` (texture, two BSDFs, lighting, background, tone curve,
# camera, motion blur); TEST_VARIANTS rendered for testing only (`clothgap render --test-variant`; default
# heldout: lighting, tone curve and camera changed at once, a look no model trains on).
# MOTIONS (default wind). One lrcn per variant, all at once (TRAIN_ARGS). The sim stage's material analyses
# are left out (eval.sim_analysis): they are the same for every variant and the paper study measures them.
# On two H100s the render of one setting's 5,184 clips took 202-270 s, so N=24 (1,296 clips) renders the ten
# variants in ~10 min (motion blur renders four instants a frame).
set -uo pipefail
source "$(dirname "$0")/gpus.sh"
N=${N:-$([ "${ngpu:-0}" -ge 2 ] && echo 24 || echo 12)}
RUN=${RUN:-/tmp/gap}
ok_file=$RUN.variants-ok
given=${VARIANTS:-}
VARIANTS=${VARIANTS:-paper,grid,diffuse,fabric-table,lighting-random,room,filmic,camera-noise,motion-blur}
TEST_VARIANTS=${TEST_VARIANTS-heldout}
if [ "${STAGES:-}" = check ]; then
  # STAGES=check: two tiny clips under every variant on this machine first, so a variant that does not render
  # here (a plugin, a driver) costs seconds and is left out, not the study; the ones that rendered go to
  # RUN.variants-ok, which the stages below read when VARIANTS is not given.
  check=$RUN.variant-check
  check_sets=${CHECK_SETS:---set sim.device=cuda --set render.backend=cuda_ad_rgb}   # word-split on purpose
  rm -rf "$check"
  # one tiny run a variant, all at once: a variant that fails while the renderer is set up stops its own run only
  for v in ${VARIANTS//,/ } ${TEST_VARIANTS//,/ }; do
    ( python3 -m clothgap sim --preset smoke --out "$check/$v" --set sim.classes=0,53 --set sim.sequences_per_class=1 \
        --set sim.frames=6 --set train.clip_len=6 --set sim.motions=wind --set sim.remeshing=uniform1 \
        --set render.variants="$v" --set render.resolution=${RES:-112} --set render.spp=${SPP:-16} \
        $check_sets > "$check.$v.log" 2>&1 &&
      timeout 300 python3 -m clothgap render "$check/$v" >> "$check.$v.log" 2>&1 ) &
  done
  wait
  rendered() {
    local out= v
    for v in ${1//,/ }; do
      if [ "$(ls "$check/$v/render/$v/wind-uniform1/"*/DONE 2>/dev/null | wc -l)" = 2 ]; then out+="${out:+,}$v"
      else echo "variant $v did not render on this machine: left out of the study ($(tail -1 "$check.$v.log"))" >&2
      fi
    done
    echo "$out"
  }
  ok=$(rendered "$VARIANTS") test_ok=$(rendered "$TEST_VARIANTS")
  [[ ",$ok," == *",paper,"* ]] || { echo "paper did not render: no study"; exit 1; }
  printf 'VARIANTS=%s\nTEST_VARIANTS=%s\n' "$ok" "$test_ok" | tee "$ok_file"
  exit 0
fi
# The variants the check rendered, unless VARIANTS was given
[ -z "$given" ] && [ -f "$ok_file" ] && source "$ok_file"
# COMBINED=NAME adds a variant of the user's ($CLOTHGAP_VARIANTS_DIR, e.g. scripts/combined_variant.py select's)
# to the run: rendered, trained and tested beside the others, which are reused.
[ -n "${COMBINED:-}" ] && VARIANTS="$VARIANTS,$COMBINED" && RUN_SETS="--set render.variants=$VARIANTS ${RUN_SETS:-}"
nvariants=$(echo "$VARIANTS" | tr ',' '\n' | grep -c .)
render_args=$gpu_render_args
# (the eval stage takes the executor's arguments, not --test-variant: EVAL_ARGS below)
for v in ${TEST_VARIANTS//,/ }; do render_args+=" --test-variant $v"; done
RUN=$RUN EXTRA="--set sim.sequences_per_class=$N --set sim.batch_size=$((N * 54))
  --set render.variants=$VARIANTS --set train.models=lrcn --set eval.sim_analysis= ${EXTRA:-}" SPP=${SPP:-16} \
  TRAIN_ARGS=${TRAIN_ARGS:-"--parallel $nvariants"} RENDER_ARGS=${RENDER_ARGS:-$render_args} RUN_SETS=${RUN_SETS:-} \
  EVAL_ARGS=${EVAL_ARGS-$gpu_render_args} \
  exec bash scripts/gpu/paper_study.sh

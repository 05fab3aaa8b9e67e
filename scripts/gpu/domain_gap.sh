#!/usr/bin/env bash
# GPU: the domain-gap study (issue 15) on one setting at the paper preset: one simulation rendered under
# `paper` and variants that each change one render axis, one lrcn per variant (the preset's recipe), every
# model tested on every variant (paired test clips), the measured fabrics. paper_study.sh runs the stages
# (resumable, LIMIT seconds per stage, $OUT/paper_study.tgz); this only names the study's settings.
#   STAGES="sim render" LIMIT=540 bash scripts/gpu/domain_gap.sh      then STAGES=render (resumes), then
#   STAGES="train eval report" ...   (one lrcn per variant, four at a time per GPU: paper_study.sh's TRAIN_ARGS)
# On a machine of two GPUs paper_study.sh renders one worker per GPU (1.8x): N=24 renders 9 variants in ~9 min.
# N sequences per class (default 12: 648 clips, 108 test sequences); VARIANTS comma-separated.
# At N=12 a model trains on 10 sequences per class, where lrcn reads ~12 % of new simulations (docs/learning.md,
# the data-size curve): enough to see large gaps only. N=48 reads ~38 % but renders ~4.4 min per variant on an H100.
set -uo pipefail
N=${N:-12}
VARIANTS=${VARIANTS:-paper,grid,diffuse,lighting-random,room,filmic,camera-noise,motion-blur,heldout}
RUN=${RUN:-/tmp/gap} EXTRA="--set sim.sequences_per_class=$N --set sim.batch_size=$((N * 54))
  --set render.variants=$VARIANTS --set train.models=lrcn ${EXTRA:-}" SPP=${SPP:-16} \
  exec bash scripts/gpu/paper_study.sh

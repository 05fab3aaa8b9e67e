#!/usr/bin/env bash
# GPU: the domain-gap study (issue 15) on one setting at the paper preset: one simulation rendered under
# `paper` and variants that each change one render axis, one lrcn per variant (the preset's recipe), every
# model tested on every variant (paired test clips), the measured fabrics. paper_study.sh runs the stages
# (resumable, LIMIT seconds per stage, $OUT/paper_study.tgz); this only names the study's settings.
#   STAGES="sim render" LIMIT=540 bash scripts/gpu/domain_gap.sh      then STAGES=render (resumes), then
#   STAGES="train eval report" ...   (one lrcn per variant, four at a time per GPU: paper_study.sh's TRAIN_ARGS)
# On a machine of two GPUs paper_study.sh renders one worker per GPU: two H100s rendered 19 clips/s (5,184
# clips of 40 frames in 270 s), so N=24 renders 9 variants in ~10 min.
# N sequences per class (default 24 on a machine of several GPUs, else 12); VARIANTS comma-separated.
# Accuracy is data-limited (docs/learning.md: 45.6 % at 35 training sequences a class, 62.7 % at 70), so at
# N=24 (18 training sequences a class) expect large gaps only; within one bin, stretching and bending say more.
set -uo pipefail
ngpu=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true)
N=${N:-$([ "${ngpu:-0}" -ge 2 ] && echo 24 || echo 12)}
VARIANTS=${VARIANTS:-paper,grid,diffuse,lighting-random,room,filmic,camera-noise,motion-blur,heldout}
RUN=${RUN:-/tmp/gap} EXTRA="--set sim.sequences_per_class=$N --set sim.batch_size=$((N * 54))
  --set render.variants=$VARIANTS --set train.models=lrcn ${EXTRA:-}" SPP=${SPP:-16} \
  exec bash scripts/gpu/paper_study.sh

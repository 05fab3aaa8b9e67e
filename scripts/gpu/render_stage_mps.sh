# Issue 14: the render stage itself under CUDA MPS, 2,592 wind clips at 112 px 16 spp on four H100s, from one
# simulation: one worker a GPU (the multi-GPU default), four a GPU without MPS, four a GPU under an MPS control daemon.
# Figures: benchmarks/results/render_stage-mps-h100x4-n2592.json (2026-11-26) and readme-multi-h100x4-20261127.json.
# Run on the device after staging the bundle. Each mode's stage summary (its own clock) goes to $OUT/render_stage.json.
source scripts/gpu/env.sh; unset CUDA_VISIBLE_DEVICES
rm -f $OUT/summary.txt       # one line a mode, of this run only
RUN=/tmp/w STAGES=sim SEQ=48 SPP=16 bash scripts/gpu/paper_study.sh > $OUT/sim.log 2>&1; tail -3 $OUT/sim.log
for mode in gpw1 gpw025 gpw025-mps; do
  rm -rf /tmp/w/render
  gpw=0.25; [ $mode = gpw1 ] && gpw=1
  # the first two without MPS (clothgap now starts its own daemon for shared GPUs); the third under the daemon
  # this script starts (clothgap uses a daemon already running as it is)
  mps=off; [ $mode = gpw025-mps ] && mps=auto
  if [ $mode = gpw025-mps ]; then export CUDA_MPS_PIPE_DIRECTORY=/tmp/mps-pipe CUDA_MPS_LOG_DIRECTORY=/tmp/mps-log; mkdir -p /tmp/mps-pipe /tmp/mps-log; nvidia-cuda-mps-control -d; fi
  t0=$(date +%s.%N); timeout 150 python3 -m clothgap render /tmp/w --executor process --gpus-per-worker $gpw --cuda-mps $mps > $OUT/render-$mode.log 2>&1; rc=$?; t1=$(date +%s.%N)
  n=$(ls /tmp/w/render/*/wind-uniform1/*/DONE 2>/dev/null | wc -l)
  echo "$mode rc=$rc seconds=$(python3 -c "print(round($t1-$t0,1))") clips_done=$n" | tee -a $OUT/summary.txt
done
echo quit | nvidia-cuda-mps-control; cp -r /tmp/mps-log $OUT/ 2>/dev/null; ls /tmp/w/render/
python3 scripts/stage_summaries.py gpw1=$OUT/render-gpw1.log gpw025=$OUT/render-gpw025.log \
  gpw025-mps=$OUT/render-gpw025-mps.log --out $OUT/render_stage.json > /dev/null

#!/usr/bin/env bash
# GPU: one setting of the paper's study at full size through the real CLI, stage by stage.
#   STAGES="sim render" bash scripts/gpu/paper_study.sh     (then "train", then "eval report")
#   SEQ=48 simulates the paper's 48 sequences per class instead of the preset's 384 (an eighth of the render time).
#   RENDER_ARGS: the default is gpus.sh's gpu_render_args (four workers a GPU under clothgap's MPS daemon).
#   TRAIN_ARGS (default "--parallel <4 x GPUs>") trains that many models at once over the machine's GPUs.
#   EVAL_ARGS (default RENDER_ARGS) spreads the simulation and rendering of the measured-fabric set over the same
#   workers (without MPS unless it adds --cuda-mps on: --cuda-mps auto serves the render stage only).
#   SIM_ARGS (default gpus.sh's gpu_sim_args: one worker a GPU where there are several, else one process);
#   "--executor process --workers 2 --gpus-per-worker 0.5" simulates two shards on one GPU, so one's host work
#   (an adaptive setting's health, remesh and rebuild: a third of its stage) overlaps the other's steps.
#   The paper preset packs the network's frames alone (render.pack_frames: one array a setting);
#   EXTRA='--set render.write_png=true' adds the PNGs (the cost every clip paid before). The render line's summary has frames and seconds: frames/s over the
#   ceiling of scripts/gpu/render_bench.sh (RESOLUTIONS=112) on the same machine is the render's ratio.
# Every stage resumes, so a call cut off at the device's 10-minute limit loses nothing:
# call again with the same STAGES. Timings accumulate in $RUN/gpu_timings.jsonl; each
# call copies them, the config and the eval tables to $OUT (one tarball). RUN_SETS="--set ..." applies to a
# run that exists (e.g. variants added to it). BUDGET (seconds, as scripts/gpu/queue.sh gives) bounds each stage
# by what is left of it when LIMIT is not set. Exit status: 0 when every stage finished, 75 when one was cut
# off by its time limit (call again), 1 when one failed.
set -uo pipefail
source scripts/gpu/env.sh
RUN=${RUN:-/tmp/paper_study}
STAGES=${STAGES:-"sim render train eval report"}
# Batches of 2,592 cloths, adaptive ones too: 3.7 GB of GPU memory per 432 adaptive cloths since the leak fix
# (docs/simulation.md), ~19 GB for 2,592 (the preset's 384 sequences a class are eight batches a setting).
# BATCH=N cuts a setting into batches of N cloths.
# PRESET=study runs that preset as it is (its twelve datasets; SEQ and EXTRA still apply).
PRESET=${PRESET:-paper}
if [ "$PRESET" = paper ]; then
  SETS=(--set sim.motions=${MOTIONS:-wind} --set sim.remeshing=${REMESHING:-uniform1} --set sim.batch_size=${BATCH:-2592}
        --set render.resolution=${RES:-112} --set render.spp=${SPP:-8}
        ${SEQ:+--set sim.sequences_per_class=$SEQ} ${EXTRA:-})
else
  SETS=(${BATCH:+--set sim.batch_size=$BATCH} ${SEQ:+--set sim.sequences_per_class=$SEQ} ${EXTRA:-})
fi
# Every GPU of the machine: render shards four workers a GPU under MPS,
# training runs four models at a time per GPU (a model leaves most of an H100 idle). Set to override.
source "$(dirname "$0")/gpus.sh"
SIM_ARGS=${SIM_ARGS-$gpu_sim_args}
RENDER_ARGS=${RENDER_ARGS-$gpu_render_args}
TRAIN_ARGS=${TRAIN_ARGS-"--parallel $((4 * ngpu))"}
EVAL_ARGS=${EVAL_ARGS-$RENDER_ARGS}
started=$(date +%s) status=0 fixed_limit=${LIMIT:-}
for stage in $STAGES; do
  t0=$(date +%s.%N)
  [ -z "$fixed_limit" ] && [ -n "${BUDGET:-}" ] && LIMIT=$(( BUDGET - ($(date +%s) - started) - 10 ))
  [ -n "${LIMIT:-}" ] && [ "$LIMIT" -lt 20 ] && { echo "no time left for $stage: call again"; status=75; break; }
  # (report takes no settings: it shows the run as it is)
  sets=${RUN_SETS:-}; [ "$stage" = report ] && sets=
  if [ -f "$RUN/config.json" ]; then args=("$RUN" $sets); else args=(--preset "$PRESET" --out "$RUN" "${SETS[@]}"); fi
  extra=(); [ "$stage" = sim ] && extra=(${SIM_ARGS:-})
  [ "$stage" = render ] && extra=(${RENDER_ARGS:-}); [ "$stage" = train ] && extra=(${TRAIN_ARGS:-})
  [ "$stage" = eval ] && extra=(${EVAL_ARGS:-})
  # GPU memory and utilisation sampled while the stage runs (after it ends the process has freed it all): the
  # peak memory of any GPU, and the mean share of time a kernel ran (whether a stage keeps its GPUs busy).
  samples="/tmp/gpu_samples_$(basename "$RUN")_$stage.txt"
  nvidia-smi ${gpus:+-i $gpus} --query-gpu=memory.used,utilization.gpu --format=csv,noheader,nounits -lms 500 > "$samples" 2>/dev/null &
  sampler=$!
  # The host's memory every half second (scripts/gpu/host_sample.sh: the machine's memory in use, its Shmem, and
  # whose it is: the Python processes' private memory and the MPS server's): the stage's peak over what was in use
  # when it started (issue 14: host memory flat across settings). The loop ends with this script.
  host_samples="/tmp/host_samples_$(basename "$RUN")_$stage.txt"
  rm -f "$host_samples"
  (while kill -0 $$ 2>/dev/null; do
     bash "$(dirname "$0")/host_sample.sh"
     sleep 0.5; done) > "$host_samples" 2>/dev/null &
  host_sampler=$!
  # LIMIT (seconds, optional) stops the stage in time for the call's 10 minutes; it resumes next call.
  # The stage's log (progress bars left out) in full to $OUT (this call's; a resumed stage starts a new one), its
  # last lines here, and the train stage's time before any model started and each wave's time, which would
  # otherwise scroll past.
  stage_log="/tmp/stage_log_$(basename "$RUN")_$stage.txt"
  ${LIMIT:+timeout -k 10 "$LIMIT"} python3 -m clothgap $stage "${args[@]}" "${extra[@]}" 2>&1 | tr '\r' '\n' | grep -vE "it/s\]|clip/s\]|shard/s\]|s/it\]|clip-frame/s\]" > "$stage_log"
  rc=${PIPESTATUS[0]}
  tail -8 "$stage_log" > "$stage_log.tail"
  grep -E "ready in|^train: wave" "$stage_log" | tail -3 | grep -vxF -f "$stage_log.tail"     # (not twice)
  cat "$stage_log.tail"
  cp "$stage_log" "$OUT/" 2>/dev/null
  t1=$(date +%s.%N)
  kill $sampler $host_sampler 2>/dev/null; wait $sampler $host_sampler 2>/dev/null
  python3 - "$samples" "$stage" "$rc" "$t0" "$t1" "$host_samples" "$(dirname "$0")/.." >> "$RUN/gpu_timings.jsonl" <<'PY'
import json, sys
from pathlib import Path
path, stage, rc, t0, t1, host_path, scripts = sys.argv[1:]
sys.path.insert(0, scripts)
from host_samples import read_samples      # scripts/host_samples.py: the samples as its summaries read them
try:
    samples = [s for s in read_samples(Path(host_path))[0] if len(s) == 5]
except SystemExit:                          # no sample: the stage ended within the first half second
    samples = []
host = [(u, m) for u, m, *_ in samples]
rows = []
try:
    for line in open(path):
        parts = [x.strip() for x in line.split(",")]
        if len(parts) == 2 and all(x.replace(".", "", 1).isdigit() for x in parts):
            rows.append((float(parts[0]), float(parts[1])))
except OSError:
    pass
print(json.dumps({"stage": stage, "rc": int(rc), "seconds": round(float(t1) - float(t0), 1),
                  "peak_gpu_mib": int(max((m for m, _ in rows), default=0)),
                  "mean_gpu_util_pct": round(sum(u for _, u in rows) / len(rows), 1) if rows else None,
                  "host_used_mib_at_start": host[0][0] if host else None,
                  "peak_host_mib_over_start": max(u for u, _ in host) - host[0][0] if host else None,
                  "peak_host_shmem_mib_over_start": max(m for _, m in host) - host[0][1] if host else None,
                  "peak_python_anon_mib": max((s[2] for s in samples), default=None),
                  "peak_python_processes": max((s[3] for s in samples), default=None),
                  "peak_mps_anon_mib": max((s[4] for s in samples), default=None)}))
PY
  case $rc in
    0) ;;
    124|137) status=75; break ;;
    *) status=1; break ;;
  esac
done
cat "$RUN/gpu_timings.jsonl"
# The calls so far summed per stage (benchmarks/study.py --timings): the study's cost as one result file.
python3 benchmarks/study.py --timings "$RUN" --out "$OUT/study-timings.json" > /dev/null 2>&1 || true
# The report (images embedded) and the eval's per-clip predictions in tarballs of their own: the device brings back
# files of at most 16 MiB (the queue leaves out the largest first), and the numbers must come back even when those
# do not.
cd "$RUN" && tar czf "$OUT/paper_study.tgz" config.json gpu_timings.jsonl train/index.json \
  $(ls -d train/*/*/*/s*/metrics.csv train/*/*/*/s*/val_predictions.csv eval/*.csv eval/*.md eval/*.json 2>/dev/null) 2>/dev/null
[ -d eval/predictions ] && tar czf "$OUT/paper_study-predictions.tgz" eval/predictions
[ -f report/report.html ] && tar czf "$OUT/paper_study-report.tgz" report/report.html
ls -la "$OUT"
exit $status

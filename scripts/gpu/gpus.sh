# Sourced by the GPU scripts: gpus (this process's GPUs as CUDA_VISIBLE_DEVICES entries, as
# clothgap.executor.visible_gpus reads them: that variable when set, else nvidia-smi's list; empty when there are
# none) and ngpu (their count, at least 1, as a size). A lane of scripts/gpu/lanes.sh sees only its own GPUs, so a
# script sizes its work and samples memory by its lane, not by the whole machine. PYTHON names the interpreter
# (default python3, the one that imports the project).
gpus=$("${PYTHON:-python3}" -c 'from clothgap.executor import visible_gpus; print(",".join(visible_gpus()))') ||
  { echo "gpus.sh: ${PYTHON:-python3} cannot import clothgap.executor (is the project on PYTHONPATH?)" >&2; exit 2; }
ngpu=$(echo "$gpus" | tr ',' '\n' | grep -c . || true); [ "${ngpu:-0}" -ge 1 ] || ngpu=1
# gpu_render_args: how the scripts render where there are GPUs, four workers a GPU under clothgap's private CUDA MPS
# daemon (--cuda-mps auto): 2.2x one worker a GPU on four H100s (benchmarks/results/render_stage-mps-h100x4-n2592.json),
# where four a GPU without MPS gained nothing; empty without GPUs (a CPU dry run renders in one process).
gpu_render_args=; [ -n "$gpus" ] && gpu_render_args="--executor process --gpus-per-worker 0.25"
# gpu_sim_args: with several GPUs, one simulation worker a GPU (the study's sim ran so on four H100s,
# study-h100x4.json); one GPU or none: one process (a setting's 20,736 uniform clips took 81.8 s on one of four
# H100s while three idled, learn_data384-arm-uniform1-h100x4.json).
gpu_sim_args=; [ -n "$gpus" ] && [ "$ngpu" -gt 1 ] && gpu_sim_args="--executor process --workers $ngpu --gpus-per-worker 1"

# Sourced by the GPU scripts: gpus (this process's GPUs as CUDA_VISIBLE_DEVICES entries, as
# clothgap.executor.visible_gpus reads them: that variable when set, else nvidia-smi's list; empty when there are
# none) and ngpu (their count, at least 1, as a size). A lane of scripts/gpu/lanes.sh sees only its own GPUs, so a
# script sizes its work and samples memory by its lane, not by the whole machine. PYTHON names the interpreter
# (default python3, the one that imports the project).
gpus=$("${PYTHON:-python3}" -c 'from clothgap.executor import visible_gpus; print(",".join(visible_gpus()))') ||
  { echo "gpus.sh: ${PYTHON:-python3} cannot import clothgap.executor (is the project on PYTHONPATH?)" >&2; exit 2; }
ngpu=$(echo "$gpus" | tr ',' '\n' | grep -c . || true); [ "${ngpu:-0}" -ge 1 ] || ngpu=1

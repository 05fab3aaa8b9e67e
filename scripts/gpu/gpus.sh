# Sourced by the GPU scripts: gpus (this process's GPUs as CUDA_VISIBLE_DEVICES entries: that variable when
# set, else every GPU nvidia-smi lists; empty when there are none) and ngpu (their count, at least 1, as a
# size). A lane of scripts/gpu/lanes.sh sees only its own GPUs, so a script sizes its work and samples memory
# by its lane, not by the whole machine. Blank and -1 entries are dropped, as clothgap.executor.visible_gpus
# drops them.
if [ -n "${CUDA_VISIBLE_DEVICES+x}" ]; then gpus=$CUDA_VISIBLE_DEVICES
elif listed=$(nvidia-smi --query-gpu=index --format=csv,noheader 2>/dev/null); then
  gpus=$(echo "$listed" | grep -E '^[[:space:]]*[0-9]+[[:space:]]*$' | tr -d ' ' | paste -sd, -)
else gpus=
fi
gpus=$(echo "$gpus" | tr ',' '\n' | tr -d ' ' | awk '$0 != "" && $0 != "-1"' | paste -sd, -)
ngpu=$(echo "$gpus" | tr ',' '\n' | grep -c . || true); [ "${ngpu:-0}" -ge 1 ] || ngpu=1

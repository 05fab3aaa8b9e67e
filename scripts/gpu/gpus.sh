# Sourced by the GPU scripts: gpus (this process's GPUs as CUDA_VISIBLE_DEVICES entries: that variable when
# set, else every GPU nvidia-smi lists) and ngpu (their count, at least 1). A lane of scripts/gpu/lanes.sh sees
# only its own GPUs, so a script sizes its work and samples memory by its lane, not by the whole machine.
if [ -n "${CUDA_VISIBLE_DEVICES+x}" ]; then gpus=$CUDA_VISIBLE_DEVICES
else gpus=$(nvidia-smi --query-gpu=index --format=csv,noheader 2>/dev/null | tr -d ' ' | paste -sd, -)
fi
ngpu=$(echo "$gpus" | tr ',' '\n' | grep -c . || true); [ "${ngpu:-0}" -ge 1 ] || ngpu=1

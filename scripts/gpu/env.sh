# Source on the GPU machine after the bundle is staged (../shared/gpu/README.md):
# puts Mitsuba/Warp/OpenEXR (the bundle), PyAV (.whl/, carried) and the project on the path.
source /tmp/gpu-env.sh
if ls .whl/*.whl >/dev/null 2>&1 && [ ! -d /tmp/site/av ]; then
  python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
fi
export PYTHONPATH=$PYTHONPATH:/tmp/site
# Warp's kernel cache in one place for every call on this machine, seeded with the simulation's kernels compiled
# ahead of time (scripts/gpu/warp_aot.py, carried as .gpu/warp-aot): a fresh machine then compiles none of them.
export WARP_CACHE_PATH=/tmp/warp-cache
mkdir -p "$WARP_CACHE_PATH"
# (once a machine, before anything has compiled into the cache)
if [ -d .gpu/warp-aot ] && [ ! -f "$WARP_CACHE_PATH/.aot-copied" ]; then
  cp -r .gpu/warp-aot/. "$WARP_CACHE_PATH/" && touch "$WARP_CACHE_PATH/.aot-copied"
fi
export OUT=${OUT:-/tmp/out}
# NVLink multicast stays off on machines of several GPUs: a program that uses it can take the host's
# shared GPUs out of service (the device tool's KINDS.md); child processes inherit these.
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader

# Sourced by the device scripts, from the repository root on a lent GPU machine: installs the
# carried wheels (../shared/gpu/wheelhouse.sh builds them into .wheels) unless present, sets the
# environment, makes $OUT and $R (/tmp/lanes), and defines log (seconds since the start, to
# $OUT/log.txt); it logs the machine's GPUs.
set -uo pipefail
if ls .wheels/*.whl >/dev/null 2>&1 && ! python3 -c "import mujoco, brax" 2>/dev/null; then
  python3 -m pip install -q --no-deps --no-index .wheels/*.whl 2>&1 | grep -v -i warn | tail -2
fi
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 TTMJX_JAX_CACHE=$PWD/.jax_cache XLA_PYTHON_CLIENT_PREALLOCATE=false
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; R=${R:-/tmp/lanes}; mkdir -p "$R"
t0=$(date +%s)
log() { echo "$(( $(date +%s) - t0 ))s $*" | tee -a "$OUT/log.txt"; }
log "start $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | tr '\n' ' ')"

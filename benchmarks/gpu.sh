#!/bin/sh
# The GPU record of benchmarks/throughput.py: panda RK4 rollouts up to B = 2^20 on one GPU,
# jaxbody float32 and float64 with the vectorised kernel and MJX in one record, then jaxbody
# with kernel "auto" (the unrolled kernel off the CPU) in a second record, on the same machine.
#
#   sh benchmarks/gpu.sh OUT_DIR [NAME]
#
# Needs a CUDA build of JAX. Packages missing there may come as wheels in .whl/ (mujoco,
# mujoco-mjx, diffrax, equinox, ...): they are installed into /tmp/site first. Each stage has
# its own time limit, and the records (OUT_DIR/NAME.{md,json,png}) are rewritten after each
# worker, so a run cut short keeps what it measured.
set -u
out=${1:?usage: sh benchmarks/gpu.sh OUT_DIR [NAME]}
name=${2:-throughput_gpu}
py=${PYTHON:-python3}
if ls .whl/*.whl >/dev/null 2>&1; then
  $py -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv
$py -c "import jax; print(jax.__version__, jax.devices(), jax.devices()[0].device_kind)" || exit 1
start=$(date +%s)
common="--models panda --devices 1 --chunk 2000000 --single-steps 0 --no-accuracy --steps 100 --max-work 20000000
  --min-time 0.3 --repeats 3 --out $out"
# 1. the vectorised kernel (compiles in seconds), float32, MJX, float64: one complete record
timeout 330 $py benchmarks/throughput.py $common --kernel vectorised --batches "${BATCHES:-1024,65536,1048576}" \
  --impls jb32,mjx,jb64 --mjx-batches "${MJX_BATCHES:-65536,1048576}" --timeout 120 --mjx-timeout 110 \
  --name "${name}" --note "GPU run (benchmarks/gpu.sh), kernel vectorised. ${NOTE:-}"
echo "gpu.sh: vectorised record done at $(( $(date +%s) - start )) s"
# 2. kernel auto (the unrolled straight-line kernel off the CPU), in the time left
left=$(( ${BUDGET:-545} - ($(date +%s) - start) ))
[ "$left" -gt 60 ] || exit 0
timeout "$left" $py benchmarks/throughput.py $common --kernel auto --batches "${BATCHES_AUTO:-65536,1048576}" \
  --impls jb32,jb64 --timeout $(( left / 2 )) --name "${name}_auto" \
  --note "GPU run (benchmarks/gpu.sh), kernel auto (unrolled), right after ${name} on the same machine. ${NOTE:-}"
echo "gpu.sh: done at $(( $(date +%s) - start )) s"

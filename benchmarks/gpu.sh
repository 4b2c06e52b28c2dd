#!/bin/sh
# The GPU records of benchmarks/throughput.py: panda RK4 rollouts on one GPU.
#
#   sh benchmarks/gpu.sh OUT_DIR [NAME]
#
# Stages (STAGES, default "vectorised auto"), each a throughput.py run with its own time limit
# and its own record OUT_DIR/NAME[_suffix].{md,json,png}, rewritten after each worker (a run
# cut short keeps what it measured):
#   vectorised  jaxbody float32 and float64 with the vectorised kernel and MJX, B up to 2^20 (NAME)
#   auto        jaxbody float32 and float64 with kernel "auto", the unrolled kernel off the CPU (NAME_auto)
#   pair        jaxbody float32 (kernel auto) and MJX at BATCHES_PAIR (default 65536) (NAME_pair)
#   graphs      the pair again, with XLA recording each whole step loop (jaxbody's and MJX's)
#               as one CUDA graph: --xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL (NAME_graphs)
# Every record lists the operations of one loop iteration (loop_body_ops in its JSON).
#
# Needs a CUDA build of JAX. Packages missing there may come as wheels in .whl/ (mujoco,
# mujoco-mjx, diffrax, equinox, ...): they are installed into /tmp/site first.
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
pair="--kernel auto --impls jb32,mjx --batches ${BATCHES_PAIR:-65536} --mjx-batches ${BATCHES_PAIR:-65536}"
for stage in ${STAGES:-vectorised auto}; do
  case $stage in
  vectorised)
    timeout 330 $py benchmarks/throughput.py $common --kernel vectorised --batches "${BATCHES:-1024,65536,1048576}" \
      --impls jb32,mjx,jb64 --mjx-batches "${MJX_BATCHES:-65536,1048576}" --timeout 120 --mjx-timeout 110 \
      --name "${name}" --note "GPU run (benchmarks/gpu.sh), kernel vectorised. ${NOTE:-}" ;;
  auto)
    left=$(( ${BUDGET:-545} - ($(date +%s) - start) ))
    [ "$left" -gt 60 ] || continue
    timeout "$left" $py benchmarks/throughput.py $common --kernel auto --batches "${BATCHES_AUTO:-65536,1048576}" \
      --impls jb32,jb64 --timeout $(( left / 2 )) --name "${name}_auto" \
      --note "GPU run (benchmarks/gpu.sh), kernel auto (unrolled), after the vectorised stage on the same machine. ${NOTE:-}" ;;
  pair)
    timeout 220 $py benchmarks/throughput.py $common $pair --timeout 150 --mjx-timeout 100 --name "${name}_pair" \
      --note "GPU run (benchmarks/gpu.sh, stage pair): kernel auto (unrolled) float32 and MJX, XLA's default flags. ${NOTE:-}" ;;
  graphs)
    XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL" \
    timeout 220 $py benchmarks/throughput.py $common $pair --timeout 150 --mjx-timeout 100 --name "${name}_graphs" \
      --note "GPU run (benchmarks/gpu.sh, stage graphs): as stage pair, each whole loop one CUDA graph. ${NOTE:-}" ;;
  *) echo "gpu.sh: unknown stage $stage"; exit 2 ;;
  esac
  echo "gpu.sh: stage $stage done at $(( $(date +%s) - start )) s"
done

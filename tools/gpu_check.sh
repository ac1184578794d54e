#!/usr/bin/env bash
# The whole GPU check in one script, under 9 minutes, with JAX alone (no TensorFlow) on the machine's first JAX device:
#   1. latency of FastFlow3D's exported forward (paper config, 32K / 100K / 255K / 1M points; float32, tf32, bfloat16),
#      printed beside the paper's P100 figures;
#   2. the exported training step (forward, loss, backward, Adam; WOD's average 177K points, batch 1 and 8), in ms per
#      step and per pair: the accelerator's input rate for the README's sizing table;
#   3. what the device computes on fixed inputs against TensorFlow's results saved at export (flow, loss, gradient
#      norm), so a wrong GPU lowering shows.
#
#   tools/gpu_check.sh [EXPORT_DIR] [OUT_JSON] [more tools/run_xla.py flags, e.g. --precisions float32]
#
# EXPORT_DIR (default .devcarry/xla_paper) is made beforehand, on any CPU machine with TensorFlow and the xla extra:
#   python tools/export_xla.py --config configs/fastflow3d_waymo.yaml --points 32000,100000,255000,1000000 \
#       --precisions float32,tf32,bfloat16 --train_points 177000 --train_batch_sizes 1,8 --reference \
#       --out .devcarry/xla_paper                                            # random weights, ~35 MB
# OUT_JSON defaults to $OUT/xla_latency_gpu.json where $OUT is set, else benchmarks/xla_latency_gpu.json; it is
# rewritten after every artifact. Relative paths are taken from the repository root.
# The GPU machine needs python3 with jax[cuda], flatbuffers and numpy. Environment knobs: PYTHON (python3), RUNS (90)
# and WARMUP (10) as in the paper's latency appendix, TRAIN_RUNS (30 training steps per artifact), BUDGET_S (420: no
# artifact starts later; the rest are listed as skipped), LIMIT_S (510: the runner is stopped after this).
set -euo pipefail
cd "$(dirname "$0")/.."
EXPORT_DIR=${1:-.devcarry/xla_paper}
OUT_JSON=${2:-${OUT:-benchmarks}/xla_latency_gpu.json}
shift $(( $# < 2 ? $# : 2 ))
PYTHON=${PYTHON:-python3}
RUNS=${RUNS:-90}
WARMUP=${WARMUP:-10}
TRAIN_RUNS=${TRAIN_RUNS:-30}
BUDGET_S=${BUDGET_S:-420}
LIMIT_S=${LIMIT_S:-510}

if [ ! -f "$EXPORT_DIR/manifest.json" ]; then
  echo "gpu_check: no $EXPORT_DIR/manifest.json; make it first with tools/export_xla.py (see the top of $0)" >&2
  exit 2
fi
du -sh "$EXPORT_DIR"
if command -v nvidia-smi >/dev/null; then
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
fi
"$PYTHON" - <<'PY'
import jax
device = jax.devices()[0]
print(f"python jax {jax.__version__}, default device {device.platform}: {getattr(device, 'device_kind', device)}")
if device.platform != "gpu":
    print("gpu_check: WARNING no GPU visible to JAX; the timings below are for", device.platform)
PY
export PYTHONUNBUFFERED=1
timeout "$LIMIT_S" "$PYTHON" tools/run_xla.py "$EXPORT_DIR" --runs "$RUNS" --warmup "$WARMUP" --train_runs "$TRAIN_RUNS" \
  --budget_s "$BUDGET_S" \
  --out "$OUT_JSON" "$@"
echo "gpu_check: wrote $OUT_JSON"

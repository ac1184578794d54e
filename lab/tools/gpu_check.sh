#!/usr/bin/env bash
# The whole GPU check in one script, under 9 minutes, with JAX alone (no TensorFlow) on the machine's first JAX device:
#   1. latency of FastFlow3D's exported forward (paper config, 32K / 100K / 255K / 1M points; float32, tf32, bfloat16),
#      printed beside the paper's P100 figures;
#   2. the exported training step (forward, loss, backward, Adam; WOD's average 177K points, batch 1 and 8), in ms per
#      step and per pair: the accelerator's input rate for the README's sizing table;
#   3. what the device computes on fixed inputs against TensorFlow's results saved at export (flow, loss, gradient
#      norm), so a wrong GPU lowering shows;
#   4. when GRU_DIR holds an export of the model with DeFlow's GRU head (`model.head=gru`): 1-2 for it, its
#      rows in their own JSON beside the paper head's;
#   5. where the forward's time goes (lab/tools/profile_xla.py): the bfloat16 forward at PROFILE_POINTS, its weights
#      also compiled in as constants, and every variant the export holds (--variants below), device time per HLO
#      instruction by kind and by the paper table's row, into xla_profile_gpu.json beside OUT_JSON;
#   6. when NSFP_DIR holds an export: NSFP's per-pair optimiser (distance grids and Adam steps; the
#      pseudo-label job's two-sided fit) fitting 150K points and 37.5K (a 150K pair as the job fits it, every 4th
#      point): seconds per step, per grid, per pair (the issue's target: <= 1 s per pair at 150K points), and its
#      grids, loss and motion against TensorFlow's.
#
#   lab/tools/gpu_check.sh [EXPORT_DIR] [OUT_JSON] [more lab/tools/run_xla.py flags, e.g. --precisions float32]
#
# EXPORT_DIR (default .devcarry/xla_paper) is made beforehand, on any CPU machine with TensorFlow and the xla extra:
#   python tools/export_xla.py --config configs/fastflow3d_waymo.yaml --points 32000,100000,255000,1000000 \
#       --precisions float32,tf32,bfloat16 --train_points 177000 --train_batch_sizes 1,8 \
#       --train_precisions float32,bfloat16 --reference --variants fold_bn,one_chunk,fold_bn+one_chunk \
#       --variant_points 32000,1000000 --variant_precisions bfloat16 --out .devcarry/xla_paper  # random weights, ~30 MB
# GRU_DIR (default .devcarry/xla_gru; skipped when absent) likewise, with --set model.head=gru, fewer artifacts and no
# reference (its 1M-point inputs would take the three exports past the 64 MiB a device call carries; the GRU head's
# export is checked against TensorFlow on the CPU, tests/training/test_xla_step.py), ~20 MB. Weights and references
# are compressed: the three exports and the tracked tree together fit a device call.
#   python tools/export_xla.py --config configs/fastflow3d_waymo.yaml --set model.head=gru --points 32000,1000000 \
#       --precisions float32,bfloat16 --train_points 177000 --train_batch_sizes 1 --out .devcarry/xla_gru
# NSFP_DIR (default .devcarry/nsfp_xla; skipped when absent) likewise, ~3 minutes on 2 CPU cores (the reference: 50
# of TensorFlow's steps at 37.5K points):
#   python tools/export_nsfp_xla.py --points 150000,37500 --segment_steps 50 --precisions float32,tf32 \
#       --reference_calls 1 --reference_points 37500 --out .devcarry/nsfp_xla   # synthetic pairs, ~3 MB
# OUT_JSON defaults to $OUT/xla_latency_gpu.json where $OUT is set, else benchmarks/xla_latency_gpu.json; NSFP's to
# nsfp_xla_gpu.json and the GRU head's to xla_latency_gpu_gru.json beside it, each rewritten after every artifact.
# Relative paths are from the repository root.
# The GPU machine needs python3 with jax[cuda], flatbuffers and numpy. Environment knobs: PYTHON (python3), RUNS (90)
# and WARMUP (10) as in the paper's latency appendix, TRAIN_RUNS (30 training steps per artifact), LIMIT_S (510: the
# whole script's runners are stopped within this), NSFP_LIMIT_S (180 of it for NSFP when NSFP_DIR is there; the model
# gets the rest), BUDGET_S (300: no model artifact starts later; the rest are listed as skipped), NSFP_BUDGET_S (140:
# the same for NSFP entries; float32 first, with the check), NSFP_PAIR_STEPS (500 Adam steps in a timed pair),
# NSFP_PAIR_RUNS (2), GRU_LIMIT_S (120 of it for the GRU head when GRU_DIR is there), GRU_BUDGET_S (90),
# PROFILE_POINTS (32000,1000000; empty: no profile), PROFILE_LIMIT_S (110 of it for the profile).
set -euo pipefail
cd "$(dirname "$0")/../.."
EXPORT_DIR=${1:-.devcarry/xla_paper}
OUT_JSON=${2:-${OUT:-benchmarks}/xla_latency_gpu.json}
shift $(( $# < 2 ? $# : 2 ))
PYTHON=${PYTHON:-python3}
RUNS=${RUNS:-90}
WARMUP=${WARMUP:-10}
TRAIN_RUNS=${TRAIN_RUNS:-30}
BUDGET_S=${BUDGET_S:-300}
LIMIT_S=${LIMIT_S:-510}
NSFP_DIR=${NSFP_DIR:-.devcarry/nsfp_xla}
NSFP_JSON=${NSFP_JSON:-$(dirname "$OUT_JSON")/nsfp_xla_gpu.json}
NSFP_LIMIT_S=${NSFP_LIMIT_S:-180}
NSFP_BUDGET_S=${NSFP_BUDGET_S:-140}
NSFP_PAIR_STEPS=${NSFP_PAIR_STEPS:-500}
NSFP_PAIR_RUNS=${NSFP_PAIR_RUNS:-2}
GRU_DIR=${GRU_DIR:-.devcarry/xla_gru}
GRU_JSON=${GRU_JSON:-$(dirname "$OUT_JSON")/xla_latency_gpu_gru.json}
GRU_LIMIT_S=${GRU_LIMIT_S:-120}
GRU_BUDGET_S=${GRU_BUDGET_S:-90}
PROFILE_POINTS=${PROFILE_POINTS-32000,1000000}
PROFILE_JSON=${PROFILE_JSON:-$(dirname "$OUT_JSON")/xla_profile_gpu.json}
PROFILE_LIMIT_S=${PROFILE_LIMIT_S:-110}

if [ ! -f "$EXPORT_DIR/manifest.json" ]; then
  echo "gpu_check: no $EXPORT_DIR/manifest.json; make it first with tools/export_xla.py (see the top of $0)" >&2
  exit 2
fi
MODEL_LIMIT_S=$LIMIT_S
if [ -f "$NSFP_DIR/manifest.json" ]; then
  MODEL_LIMIT_S=$(( LIMIT_S - NSFP_LIMIT_S ))
else
  echo "gpu_check: no $NSFP_DIR/manifest.json: NSFP is not timed (tools/export_nsfp_xla.py, see the top of $0)"
fi
if [ -f "$GRU_DIR/manifest.json" ]; then
  MODEL_LIMIT_S=$(( MODEL_LIMIT_S - GRU_LIMIT_S ))
else
  echo "gpu_check: no $GRU_DIR/manifest.json: the GRU head is not timed (tools/export_xla.py, see the top of $0)"
fi
if [ -n "$PROFILE_POINTS" ]; then
  MODEL_LIMIT_S=$(( MODEL_LIMIT_S - PROFILE_LIMIT_S ))
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
status=0
timeout "$MODEL_LIMIT_S" "$PYTHON" lab/tools/run_xla.py "$EXPORT_DIR" --runs "$RUNS" --warmup "$WARMUP" \
  --train_runs "$TRAIN_RUNS" --budget_s "$BUDGET_S" --out "$OUT_JSON" "$@" || status=$?
echo "gpu_check: model runner exit status $status, results in $OUT_JSON"
if [ -n "$PROFILE_POINTS" ]; then
  timeout "$PROFILE_LIMIT_S" "$PYTHON" lab/tools/profile_xla.py "$EXPORT_DIR" --points "$PROFILE_POINTS" \
    --precision bfloat16 --bake_weights --runs "$RUNS" --warmup "$WARMUP" --out "$PROFILE_JSON" || profile_status=$?
  echo "gpu_check: profile exit status ${profile_status:-0}, results in $PROFILE_JSON"
  status=$(( status ? status : ${profile_status:-0} ))
fi
if [ -f "$GRU_DIR/manifest.json" ]; then
  du -sh "$GRU_DIR"
  timeout "$GRU_LIMIT_S" "$PYTHON" lab/tools/run_xla.py "$GRU_DIR" --runs "$RUNS" --warmup "$WARMUP" \
    --train_runs "$TRAIN_RUNS" --budget_s "$GRU_BUDGET_S" --out "$GRU_JSON" "$@" || gru_status=$?
  echo "gpu_check: GRU head runner exit status ${gru_status:-0}, results in $GRU_JSON"
  status=$(( status ? status : ${gru_status:-0} ))
fi
if [ -f "$NSFP_DIR/manifest.json" ]; then
  du -sh "$NSFP_DIR"
  timeout "$NSFP_LIMIT_S" "$PYTHON" lab/tools/run_nsfp_xla.py "$NSFP_DIR" --pair_steps "$NSFP_PAIR_STEPS" \
    --pair_runs "$NSFP_PAIR_RUNS" --budget_s "$NSFP_BUDGET_S" --out "$NSFP_JSON" || nsfp_status=$?
  echo "gpu_check: NSFP runner exit status ${nsfp_status:-0}, results in $NSFP_JSON"
  status=$(( status ? status : ${nsfp_status:-0} ))
fi
exit "$status"

"""The portable programs (written by `xla_export`): their on-disk format, loading and checks, with JAX only.

Nothing here imports TensorFlow or a module that does: a machine with JAX/XLA and no TensorFlow (a GPU box) runs the
model's compiled forward from an export directory alone; `ff3d_tf.inference.xla_timing` times it there. Layout of an
export directory:

  manifest.json                      format, grid, input/output names, the weights' order, one entry per artifact
  weights.npz                        the model's weights as plain float32 arrays (w000, w001, ...), saved once
  forward_<P>_<precision>.jaxexport  `jax.export` serialisation of the forward for P padded points, lowered for the
                                     manifest's platforms (CPU and CUDA)
  train_step_<B>x<P>_<precision>.jaxexport
                                     the training step (forward, loss, backward, Adam) for a batch of B pairs of P
                                     padded points (optional; arguments and results: `xla_export.train_step_fn`)
  reference.npz                      optional: inputs and TensorFlow's results of the first float32 artifacts, which
                                     the runner compares with what the programs compute on its device

An artifact's arguments are the weights in manifest order, then the six model inputs of `manifest["input_keys"]`
(batch B, padded points P: points_xyz_t0 [B,P,3], point_features_t0 [B,P,2], point_mask_t0 [B,P] bool, the same for
t-1 in the t0 frame); its results are flow_mps [B,P,3] (m/s) and point_valid [B,P] bool. A training step also takes
the state (weights, BatchNorm statistics, Adam's slots, iteration count) and the labels of `TRAIN_LABEL_KEYS`, and
returns the new state, the loss and the gradients' global norm.

Precisions: `float32` (every convolution and matmul at HIGHEST precision: float32-exact on GPUs with TF32), `tf32`
(DEFAULT precision: XLA may use TF32 on Ampere and later), `bfloat16` (the model's mixed_bfloat16 compute, float32
weights and point coordinates).
"""
from __future__ import annotations

import os

import numpy as np

from ff3d_tf import bench, xla_program
from ff3d_tf.xla_program import ExportFormatError  # noqa: F401  (this module's callers catch it from here)

FORMAT = "ff3d_tf.xla_forward/1"
MANIFEST_NAME = "manifest.json"
WEIGHTS_NAME = "weights.npz"
REFERENCE_NAME = "reference.npz"
PRECISIONS = ("float32", "tf32", "bfloat16")
TRAIN_LABEL_KEYS = ("flow_mps_t0", "class_id_t0")


def artifact_name(padded_points: int, precision: str) -> str:
    return f"forward_{padded_points}_{precision}.jaxexport"


def train_artifact_name(batch_size: int, padded_points: int, precision: str) -> str:
    return f"train_step_{batch_size}x{padded_points}_{precision}.jaxexport"


def read_manifest(export_dir: str) -> dict:
    return xla_program.read_manifest(export_dir, MANIFEST_NAME, FORMAT, ("weights", "input_keys", "output_keys",
                                                                         "artifacts", "grid"), "tools/export_xla.py")


def load_weights(export_dir: str, manifest: dict) -> list[np.ndarray]:
    """The weights in argument order, each checked against the manifest's shape and dtype."""
    path = os.path.join(export_dir, WEIGHTS_NAME)
    with np.load(path, allow_pickle=False) as stored:
        weights = []
        for i, spec in enumerate(manifest["weights"]):
            key = f"w{i:03d}"
            if key not in stored:
                raise ExportFormatError(f"{path}: array {key} ({spec['path']}) missing")
            w = stored[key]
            if list(w.shape) != spec["shape"] or str(w.dtype) != spec["dtype"]:
                raise ExportFormatError(f"{path}: array {key} ({spec['path']}) is {w.dtype}{list(w.shape)}, manifest "
                                        f"says {spec['dtype']}{spec['shape']}")
            weights.append(w)
    return weights


def _load_program(export_dir: str, entry: dict, num_in: int, num_out: int, expected: str):
    return xla_program.load_program(os.path.join(export_dir, entry["file"]), num_in, num_out, expected)


def load_forward(export_dir: str, entry: dict, num_weights: int):
    """The `jax.export.Exported` of one forward entry of the manifest (its argument count checked)."""
    return _load_program(export_dir, entry, num_weights + 6, 2, f"{num_weights} weights + 6 inputs -> 2 outputs")


def load_train_step(export_dir: str, entry: dict, manifest: dict):
    """The `jax.export.Exported` of one `train_artifacts` entry (its argument and result counts checked)."""
    state = len(manifest["weights"]) + 2 * manifest["num_trainable"] + 1
    return _load_program(export_dir, entry, state + 6 + len(TRAIN_LABEL_KEYS), state + 2,
                         f"{state} state arrays + 6 inputs + {len(TRAIN_LABEL_KEYS)} labels -> {state} + loss, "
                         f"grad_norm")


def random_inputs(manifest: dict, entry: dict, rng: np.random.Generator) -> list[np.ndarray]:
    """`bench.random_clouds` of `entry["points"]` points over the manifest's grid, padded to the artifact's size, in
    argument order (`manifest["input_keys"]`)."""
    g = manifest["grid"]
    clouds = bench.random_clouds(rng, entry["points"], entry["padded_points"],
                                 (g["x_range_m"], g["y_range_m"], g["z_range_m"]), entry["batch_size"])
    return [clouds[k] for k in manifest["input_keys"]]


def random_labels(entry: dict, rng: np.random.Generator) -> list[np.ndarray]:
    """`bench.random_labels` for `random_inputs`' t0 clouds, in `TRAIN_LABEL_KEYS` order."""
    labels = bench.random_labels(rng, entry["points"], entry["padded_points"], entry["batch_size"])
    return [labels[k] for k in TRAIN_LABEL_KEYS]


def initial_train_state(weights: list[np.ndarray], manifest: dict) -> list[np.ndarray]:
    """The training step's state at the start of training: the weights (trainable, then BatchNorm statistics), Adam's
    first and second moments at zero, iteration 0."""
    trainable = weights[:manifest["num_trainable"]]
    return (list(weights) + [np.zeros_like(w) for w in trainable] + [np.zeros_like(w) for w in trainable]
            + [np.asarray(0, np.int32)])


class CompiledForward:
    """One artifact compiled for the default JAX device, weights resident there: `(inputs) -> (flow, valid)`."""

    def __init__(self, exported, weights: list[np.ndarray]):
        import jax
        self.device = jax.devices()[0]
        self.weights = [jax.device_put(w, self.device) for w in weights]
        self.compiled, self.compile_s = xla_program.compile_program(exported)

    def on_device(self, inputs: list[np.ndarray]):
        import jax
        return [jax.device_put(x, self.device) for x in inputs]

    def __call__(self, device_inputs):
        """Outputs left on the device (call `block_until_ready` or `np.asarray` on them)."""
        return self.compiled(*self.weights, *device_inputs)

    def numpy(self, inputs: list[np.ndarray]) -> dict:
        """Host arrays in, host arrays out: {"flow_mps": [B,P,3], "point_valid": [B,P]}."""
        flow, valid = self(self.on_device(inputs))
        return {"flow_mps": np.asarray(flow), "point_valid": np.asarray(valid)}


class CompiledTrainStep:
    """One training-step artifact compiled for the default JAX device, its state resident there and updated in place
    (donated buffers): `step(device_batch)` -> (loss, grad_norm) on the device."""

    def __init__(self, exported, state: list[np.ndarray]):
        import jax
        self.device = jax.devices()[0]
        self.num_state = len(state)
        self.state = [jax.device_put(x, self.device) for x in state]
        self.compiled, self.compile_s = xla_program.compile_program(exported, range(self.num_state))

    def on_device(self, batch: list[np.ndarray]):
        import jax
        return [jax.device_put(x, self.device) for x in batch]

    def __call__(self, device_batch):
        results = self.compiled(*self.state, *device_batch)
        self.state = list(results[:self.num_state])
        return results[self.num_state], results[self.num_state + 1]


def load_reference(export_dir: str):
    """`REFERENCE_NAME`'s arrays (TensorFlow's inputs and results), or None when the export has none."""
    path = os.path.join(export_dir, REFERENCE_NAME)
    return dict(np.load(path)) if os.path.exists(path) else None


def check_forward(forward: CompiledForward, entry: dict, manifest: dict, ref: dict | None) -> dict | None:
    """The forward on the reference inputs against TensorFlow's flow (max |difference|, m/s) and validity (count of
    mismatches); None unless the reference has this artifact's size. Other precisions than the reference's float32
    show their own rounding."""
    if ref is None or int(ref.get("forward/padded_points", -1)) != entry["padded_points"]:
        return None
    out = forward.numpy([ref[f"forward/{k}"] for k in manifest["input_keys"]])
    return {"max_abs_flow_diff_mps": float(np.abs(out["flow_mps"] - ref["forward/out/flow_mps"]).max()),
            "valid_mismatches": int((out["point_valid"] != ref["forward/out/point_valid"]).sum())}


def check_train_step(step: CompiledTrainStep, entry: dict, manifest: dict, ref: dict | None) -> dict | None:
    """The first step from the initial state on the reference batch against TensorFlow's loss and gradient norm
    (relative differences); None unless the reference has this artifact's batch. Leaves the step's state advanced."""
    if ref is None or (int(ref.get("train/padded_points", -1)), int(ref.get("train/batch_size", -1))) != (
            entry["padded_points"], entry["batch_size"]):
        return None
    batch = [ref[f"train/{k}"] for k in manifest["input_keys"] + manifest["train_label_keys"]]
    loss, grad_norm = (float(x) for x in step(step.on_device(batch)))
    want_loss, want_norm = float(ref["train/out/loss"]), float(ref["train/out/grad_norm"])
    return {"loss_rel_diff": abs(loss - want_loss) / abs(want_loss),
            "grad_norm_rel_diff": abs(grad_norm - want_norm) / abs(want_norm)}

"""The training step's portable programs (written by `xla_step_export`): loading, running and checking them with JAX
only, on the default JAX device (the lab times them: `lab.training.xla_step_timing`).

Nothing here imports TensorFlow or a module that does: a machine with JAX/XLA and no TensorFlow (a GPU box) keeps the
training state on its device and runs steps from an export directory alone (its layout, manifest and weights:
`ff3d_tf.xla_export_dir`). A training-step artifact takes the state (weights, BatchNorm statistics, Adam's slots,
iteration count), the model inputs and the labels its loss reads (the manifest's `train_label_keys`:
`TRAIN_LABEL_KEYS` and the fields a self-supervised loss needs), and returns the new state, the loss and the
gradients' global norm (`xla_step_export.train_step_fn`).
"""
from __future__ import annotations

import numpy as np

from ff3d_tf import xla_export_dir, xla_program
from ff3d_tf.xla_export_dir import load_artifact

TRAIN_LABEL_KEYS = ("flow_mps_t0", "class_id_t0")


def train_artifact_name(batch_size: int, padded_points: int, precision: str) -> str:
    return f"train_step_{batch_size}x{padded_points}_{precision}.jaxexport"


def label_keys(manifest: dict) -> tuple[str, ...]:
    """The labels the export's training steps take, in argument order (exports written before the manifest named
    them take `TRAIN_LABEL_KEYS`)."""
    return tuple(manifest.get("train_label_keys", TRAIN_LABEL_KEYS))


def load_train_step(export_dir: str, entry: dict, manifest: dict):
    """The `jax.export.Exported` of one `train_artifacts` entry (its argument and result counts checked)."""
    state = len(manifest["weights"]) + 2 * manifest["num_trainable"] + 1
    inputs, labels = len(manifest["input_keys"]), len(label_keys(manifest))
    return load_artifact(export_dir, entry, state + inputs + labels, state + 2,
                         f"{state} state arrays + {inputs} inputs + {labels} labels -> {state} + loss, grad_norm")


def random_labels(entry: dict, manifest: dict, rng: np.random.Generator) -> list[np.ndarray]:
    """`xla_export_dir.random_labels` for `xla_export_dir.random_inputs`' clouds, in the step's label order."""
    keys = label_keys(manifest)
    labels = xla_export_dir.random_labels(rng, entry["points"], entry["padded_points"], entry["batch_size"], keys)
    return [labels[k] for k in keys]


def initial_train_state(weights: list[np.ndarray], manifest: dict) -> list[np.ndarray]:
    """The training step's state at the start of training: the weights (trainable, then BatchNorm statistics), Adam's
    first and second moments at zero, iteration 0."""
    trainable = weights[:manifest["num_trainable"]]
    return (list(weights) + [np.zeros_like(w) for w in trainable] + [np.zeros_like(w) for w in trainable]
            + [np.asarray(0, np.int32)])


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


def check_train_step(step: CompiledTrainStep, entry: dict, manifest: dict, ref: dict | None) -> dict | None:
    """The first step from the initial state on the reference batch against TensorFlow's loss and gradient norm
    (relative differences); None unless the reference has this artifact's batch. Leaves the step's state advanced."""
    if ref is None or (int(ref.get("train/padded_points", -1)), int(ref.get("train/batch_size", -1))) != (
            entry["padded_points"], entry["batch_size"]):
        return None
    batch = [ref[f"train/{k}"] for k in (*manifest["input_keys"], *label_keys(manifest))]
    loss, grad_norm = (float(x) for x in step(step.on_device(batch)))
    want_loss, want_norm = float(ref["train/out/loss"]), float(ref["train/out/grad_norm"])
    return {"loss_rel_diff": abs(loss - want_loss) / abs(want_loss),
            "grad_norm_rel_diff": abs(grad_norm - want_norm) / abs(want_norm)}

"""The forward's portable programs (written by `xla_export`): loading, running and checking them with JAX only, and
an export directory as a `ff3d_tf.predictor.Predictor`.

Nothing here imports TensorFlow or a module that does: a machine with JAX/XLA and no TensorFlow (a GPU box) runs the
model's compiled forward from an export directory alone; `lab.inference.xla_timing` times it there. The
directory's layout, manifest and weights are `ff3d_tf.xla_export_dir`'s (shared with the training step's programs).
"""
from __future__ import annotations

import numpy as np

from ff3d_tf import xla_program
from ff3d_tf.xla_export_dir import ExportFormatError, load_artifact, load_weights, read_manifest



def artifact_name(padded_points: int, precision: str) -> str:
    return f"forward_{padded_points}_{precision}.jaxexport"


def load_forward(export_dir: str, entry: dict, num_weights: int):
    """The `jax.export.Exported` of one forward entry of the manifest (its argument count checked: the weights, then
    the model inputs of `manifest["input_keys"]`, three per sweep)."""
    num_inputs = len(read_manifest(export_dir)["input_keys"])
    return load_artifact(export_dir, entry, num_weights + num_inputs, 2,
                         f"{num_weights} weights + {num_inputs} inputs -> 2 outputs")


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


def check_forward(forward: CompiledForward, entry: dict, manifest: dict, ref: dict | None) -> dict | None:
    """The forward on the reference inputs against TensorFlow's flow (max |difference|, m/s) and validity (count of
    mismatches); None unless the reference has this artifact's size. Other precisions than the reference's float32
    show their own rounding."""
    if ref is None or int(ref.get("forward/padded_points", -1)) != entry["padded_points"]:
        return None
    out = forward.numpy([ref[f"forward/{k}"] for k in manifest["input_keys"]])
    return {"max_abs_flow_diff_mps": float(np.abs(out["flow_mps"] - ref["forward/out/flow_mps"]).max()),
            "valid_mismatches": int((out["point_valid"] != ref["forward/out/point_valid"]).sum())}


class XlaPredictor:
    """An export directory's forward as a `ff3d_tf.predictor.Predictor`, with JAX: each pair runs on the smallest
    batch-1 artifact of `precision` whose bucket holds both of its clouds, padded to it with masked points (which
    change no flow). Each artifact is compiled on first use."""

    def __init__(self, export_dir: str, precision: str = "float32"):
        self.export_dir = export_dir
        self.manifest = read_manifest(export_dir)
        self.num_frames = len(self.manifest["input_keys"]) // 3  # three inputs per sweep
        self.path = export_dir
        # The order of the sweeps the model reads as the export recorded it (`ff3d_tf.inference.predictor.sweep_order`)
        self.recorded_order = {k: self.manifest[k] for k in ("partner", "temporal") if k in self.manifest}
        self.weights = load_weights(export_dir, self.manifest)
        by_size = {e["padded_points"]: e for e in self.manifest["artifacts"]
                   if e["batch_size"] == 1 and e["precision"] == precision}
        self.entries = [by_size[p] for p in sorted(by_size)]
        if not self.entries:
            raise ExportFormatError(f"{export_dir}: no forward artifact of batch 1 and precision {precision} (export "
                                    f"one: tools/export_xla.py --batch_size 1 --precisions {precision})")
        self._compiled: dict[str, CompiledForward] = {}

    def _forward(self, padded_points: int) -> tuple[CompiledForward, int]:
        """(the compiled artifact for a pair padded to `padded_points`, its own padded size)."""
        entry = next((e for e in self.entries if e["padded_points"] >= padded_points), None)
        if entry is None:
            sizes = ", ".join(str(e["padded_points"]) for e in self.entries)
            raise ValueError(f"{self.export_dir}: a pair padded to {padded_points} points is larger than every "
                             f"artifact ({sizes} points): export one that holds it (tools/export_xla.py --points "
                             f"{padded_points})")
        if entry["file"] not in self._compiled:
            exported = load_forward(self.export_dir, entry, len(self.weights))
            self._compiled[entry["file"]] = CompiledForward(exported, self.weights)
        return self._compiled[entry["file"]], entry["padded_points"]

    def predict(self, batch, example):
        inputs = {k: np.asarray(batch[k]) for k in self.manifest["input_keys"]}
        forward, size = self._forward(max(x.shape[1] for k, x in inputs.items() if k.startswith("point_mask_")))
        # [1,P,...] -> [1,size,...]: zeros, masks False
        padded = [np.pad(x, [(0, 0), (0, size - x.shape[1])] + [(0, 0)] * (x.ndim - 2))
                  for x in inputs.values()]
        out = forward.numpy(padded)
        n = int(example["num_points_t0"])
        return out["flow_mps"][0, :n], out["point_valid"][0, :n]

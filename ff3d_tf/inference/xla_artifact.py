"""The portable forward program (written by `xla_export`): its on-disk format, loading and timing, with JAX only.

Nothing here imports TensorFlow or a module that does: a machine with JAX/XLA and no TensorFlow (a GPU box) runs the
model's compiled forward from an export directory alone. Layout of an export directory:

  manifest.json                      format, grid, input/output names, the weights' order, one entry per artifact
  weights.npz                        the model's weights as plain float32 arrays (w000, w001, ...), saved once
  forward_<P>_<precision>.jaxexport  `jax.export` serialisation of the forward for P padded points, lowered for the
                                     manifest's platforms (CPU and CUDA)

An artifact's arguments are the weights in manifest order, then the six model inputs of `manifest["input_keys"]`
(batch B, padded points P: points_xyz_t0 [B,P,3], point_features_t0 [B,P,2], point_mask_t0 [B,P] bool, the same for
t-1 in the t0 frame); its results are flow_mps [B,P,3] (m/s) and point_valid [B,P] bool.

Precisions: `float32` (every convolution and matmul at HIGHEST precision: float32-exact on GPUs with TF32), `tf32`
(DEFAULT precision: XLA may use TF32 on Ampere and later), `bfloat16` (the model's mixed_bfloat16 compute, float32
weights and point coordinates).
"""
from __future__ import annotations

import json
import os
import time

import numpy as np

FORMAT = "ff3d_tf.xla_forward/1"
MANIFEST_NAME = "manifest.json"
WEIGHTS_NAME = "weights.npz"
PRECISIONS = ("float32", "tf32", "bfloat16")

# Paper, table "Inference latency varying point cloud sizes": FastFlow3D on an NVIDIA Tesla P100, batch 1, mean of 90
# forward passes after 10 warm-up passes (appendix "Measurements of Latency"). Keyed by point count.
PAPER_P100_LATENCY_MS = {32000: 49.3, 100000: 51.9, 255000: 63.1, 1000000: 98.1}
TARGET_SPEEDUP_VS_P100 = 10.0  # the GPU check's goal on an H200: <= 4.9 ms at 32K points, <= 9.8 ms at 1M


class ExportFormatError(ValueError):
    """An export directory that does not hold what its manifest says (the message names the file and field)."""


def artifact_name(padded_points: int, precision: str) -> str:
    return f"forward_{padded_points}_{precision}.jaxexport"


def read_manifest(export_dir: str) -> dict:
    path = os.path.join(export_dir, MANIFEST_NAME)
    try:
        with open(path) as f:
            manifest = json.load(f)
    except FileNotFoundError as e:
        raise ExportFormatError(f"{path}: no manifest (is {export_dir} a tools/export_xla.py output?)") from e
    except json.JSONDecodeError as e:
        raise ExportFormatError(f"{path}: not valid JSON: {e}") from e
    if manifest.get("format") != FORMAT:
        raise ExportFormatError(f"{path}: field format is {manifest.get('format')!r}, expected {FORMAT!r}")
    for key in ("weights", "input_keys", "output_keys", "artifacts", "grid"):
        if key not in manifest:
            raise ExportFormatError(f"{path}: field {key} missing")
    return manifest


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


def load_forward(export_dir: str, entry: dict, num_weights: int):
    """The `jax.export.Exported` of one manifest entry (its argument count checked)."""
    from jax import export
    path = os.path.join(export_dir, entry["file"])
    with open(path, "rb") as f:
        exported = export.deserialize(bytearray(f.read()))
    if len(exported.in_avals) != num_weights + 6 or len(exported.out_avals) != 2:
        raise ExportFormatError(f"{path}: takes {len(exported.in_avals)} arguments and returns "
                                f"{len(exported.out_avals)}, expected {num_weights} weights + 6 inputs -> 2 outputs")
    return exported


def random_inputs(manifest: dict, entry: dict, rng: np.random.Generator) -> list[np.ndarray]:
    """Two random clouds of `entry["points"]` points over the grid, padded to the artifact's size (argument order).

    Points uniform in the grid's x/y range and z in its z range, features (intensity, elongation) uniform in [0, 1]:
    the same kind of cloud as tools/benchmark_latency.py.
    """
    g = manifest["grid"]
    b, n, padded = entry["batch_size"], entry["points"], entry["padded_points"]
    arrays = []
    for _ in range(2):  # t0, then t-1 in the t0 frame
        xyz = np.zeros((b, padded, 3), np.float32)
        xyz[:, :n] = np.stack([rng.uniform(*g["x_range_m"], (b, n)), rng.uniform(*g["y_range_m"], (b, n)),
                               rng.uniform(*g["z_range_m"], (b, n))], -1)
        features = np.zeros((b, padded, 2), np.float32)
        features[:, :n] = rng.uniform(0.0, 1.0, (b, n, 2))
        mask = np.zeros((b, padded), bool)
        mask[:, :n] = True
        arrays += [xyz, features, mask]
    return arrays


class CompiledForward:
    """One artifact compiled for the default JAX device, weights resident there: `(inputs) -> (flow, valid)`."""

    def __init__(self, exported, weights: list[np.ndarray]):
        import jax
        self.device = jax.devices()[0]
        self.weights = [jax.device_put(w, self.device) for w in weights]
        avals = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.in_avals]
        start = time.perf_counter()
        self.compiled = jax.jit(exported.call).lower(*avals).compile()
        self.compile_s = time.perf_counter() - start

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


def time_forward(forward: CompiledForward, inputs: list[np.ndarray], runs: int, warmup: int) -> dict:
    """Median, mean and min latency (ms) of `runs` passes after `warmup`: inputs resident on the device; host to host.

    `median_ms` (and `mean_ms`, the paper's statistic) is the model alone (the paper's setting: clouds already on the accelerator, outputs complete there);
    `median_host_ms` adds copying the two clouds in and flow/validity back out.
    """
    device_inputs = forward.on_device(inputs)
    for _ in range(warmup):
        _block(forward(device_inputs))
        forward.numpy(inputs)
    device_times, host_times = [], []
    for _ in range(runs):
        start = time.perf_counter()
        _block(forward(device_inputs))
        device_times.append(time.perf_counter() - start)
    for _ in range(runs):
        start = time.perf_counter()
        forward.numpy(inputs)
        host_times.append(time.perf_counter() - start)
    return {"median_ms": 1e3 * float(np.median(device_times)), "mean_ms": 1e3 * float(np.mean(device_times)),
            "min_ms": 1e3 * float(np.min(device_times)),
            "median_host_ms": 1e3 * float(np.median(host_times)), "runs": runs, "warmup": warmup,
            "compile_s": forward.compile_s}


def _block(outputs):
    for x in outputs:
        x.block_until_ready()


def run_export(export_dir: str, runs: int, warmup: int, precisions=None, points=None, budget_s: float | None = None,
               seed: int = 0, log=print, on_row=None) -> dict:
    """Times every artifact of an export directory (optionally only some precisions / point counts).

    Artifacts still untimed when `budget_s` seconds have passed are listed as skipped (a GPU check must end in time).
    `on_row(result)` is called after each timed artifact with the result so far (e.g. to save partial results).
    """
    import jax
    start = time.perf_counter()
    manifest = read_manifest(export_dir)
    weights = load_weights(export_dir, manifest)
    device = jax.devices()[0]
    result = {"export_dir": export_dir, "jax": jax.__version__, "platform": device.platform,
              "device": getattr(device, "device_kind", str(device)), "num_weights": len(weights),
              "exported_with": manifest.get("exported_with", {}), "latency": [], "skipped": []}
    rng = np.random.default_rng(seed)
    compiled: dict[str, CompiledForward] = {}  # two cloud sizes of one bucket share an artifact
    for entry in manifest["artifacts"]:
        if (precisions and entry["precision"] not in precisions) or (points and entry["points"] not in points):
            continue
        if budget_s is not None and time.perf_counter() - start > budget_s:
            result["skipped"].append({"points": entry["points"], "precision": entry["precision"],
                                      "reason": f"time budget of {budget_s:.0f} s spent"})
            continue
        if entry["file"] not in compiled:
            compiled[entry["file"]] = CompiledForward(load_forward(export_dir, entry, len(weights)), weights)
        timing = time_forward(compiled[entry["file"]], random_inputs(manifest, entry, rng), runs, warmup)
        row = {"points": entry["points"], "padded_points": entry["padded_points"], "precision": entry["precision"],
               **timing}
        result["latency"].append(row)
        if on_row is not None:
            on_row(result)
        log(f"{entry['points']} points ({entry['precision']}): median {row['median_ms']:.2f} ms, min "
            f"{row['min_ms']:.2f} ms, host to host {row['median_host_ms']:.2f} ms, compile {row['compile_s']:.1f} s")
    result["total_s"] = time.perf_counter() - start
    return result


def latency_table(result: dict) -> str:
    """Markdown table of a `run_export` result beside the paper's P100 figures (speed-up = P100 mean / our median; the
    target is at least `TARGET_SPEEDUP_VS_P100` times the P100)."""
    lines = [f"FastFlow3D forward, batch 1, {result['device']} ({result['platform']}, jax {result['jax']})", "",
             "| points | precision | median ms | mean ms | min ms | host-to-host ms | paper P100 ms (mean) | "
             f"speed-up vs P100 | >= {TARGET_SPEEDUP_VS_P100:g}x |", "|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    for row in result["latency"]:
        paper = PAPER_P100_LATENCY_MS.get(row["points"])
        paper_s, speedup, met = "-", "-", "-"
        if paper:
            paper_s, speedup = f"{paper:.1f}", f"{paper / row['median_ms']:.1f}x"
            met = "yes" if paper / row["median_ms"] >= TARGET_SPEEDUP_VS_P100 else "no"
        lines.append(f"| {row['points']:,} | {row['precision']} | {row['median_ms']:.2f} | {row['mean_ms']:.2f} | "
                     f"{row['min_ms']:.2f} | "
                     f"{row['median_host_ms']:.2f} | {paper_s} | {speedup} | {met} |")
    for row in result["skipped"]:
        lines.append(f"| {row['points']:,} | {row['precision']} | skipped: {row['reason']} | | | | | | |")
    return "\n".join(lines)

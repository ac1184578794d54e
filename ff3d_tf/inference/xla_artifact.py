"""The portable programs (written by `xla_export`): their on-disk format, loading, checking and timing, with JAX only.

Nothing here imports TensorFlow or a module that does: a machine with JAX/XLA and no TensorFlow (a GPU box) runs the
model's compiled forward from an export directory alone. Layout of an export directory:

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

import json
import os
import time

import numpy as np

FORMAT = "ff3d_tf.xla_forward/1"
MANIFEST_NAME = "manifest.json"
WEIGHTS_NAME = "weights.npz"
REFERENCE_NAME = "reference.npz"
PRECISIONS = ("float32", "tf32", "bfloat16")
TRAIN_LABEL_KEYS = ("flow_mps_t0", "class_id_t0")

# Paper, table "Inference latency varying point cloud sizes": FastFlow3D on an NVIDIA Tesla P100, batch 1, mean of 90
# forward passes after 10 warm-up passes (appendix "Measurements of Latency"). Keyed by point count.
PAPER_P100_LATENCY_MS = {32000: 49.3, 100000: 51.9, 255000: 63.1, 1000000: 98.1}
TARGET_SPEEDUP_VS_P100 = 10.0  # the GPU check's goal on an H200: <= 4.9 ms at 32K points, <= 9.8 ms at 1M


class ExportFormatError(ValueError):
    """An export directory that does not hold what its manifest says (the message names the file and field)."""


def artifact_name(padded_points: int, precision: str) -> str:
    return f"forward_{padded_points}_{precision}.jaxexport"


def train_artifact_name(batch_size: int, padded_points: int, precision: str) -> str:
    return f"train_step_{batch_size}x{padded_points}_{precision}.jaxexport"


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


def _load_program(export_dir: str, entry: dict, num_in: int, num_out: int, expected: str):
    from jax import export
    path = os.path.join(export_dir, entry["file"])
    with open(path, "rb") as f:
        exported = export.deserialize(bytearray(f.read()))
    if len(exported.in_avals) != num_in or len(exported.out_avals) != num_out:
        raise ExportFormatError(f"{path}: takes {len(exported.in_avals)} arguments and returns "
                                f"{len(exported.out_avals)}, expected {expected}")
    return exported


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


def random_labels(entry: dict, rng: np.random.Generator) -> list[np.ndarray]:
    """Labels for `random_inputs`' t0 cloud (`TRAIN_LABEL_KEYS` order): flow uniform in [-10, 10] m/s and classes
    uniform in -1..4 on the real points; zero flow and class -1 (no label) on the padding."""
    b, n, padded = entry["batch_size"], entry["points"], entry["padded_points"]
    flow = np.zeros((b, padded, 3), np.float32)
    flow[:, :n] = rng.uniform(-10.0, 10.0, (b, n, 3))
    class_id = np.full((b, padded), -1, np.int32)
    class_id[:, :n] = rng.integers(-1, 5, (b, n))
    return [flow, class_id]


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


class CompiledTrainStep:
    """One training-step artifact compiled for the default JAX device, its state resident there and updated in place
    (donated buffers): `step(device_batch)` -> (loss, grad_norm) on the device."""

    def __init__(self, exported, state: list[np.ndarray]):
        import jax
        self.device = jax.devices()[0]
        self.num_state = len(state)
        self.state = [jax.device_put(x, self.device) for x in state]
        avals = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.in_avals]
        start = time.perf_counter()
        self.compiled = jax.jit(exported.call, donate_argnums=tuple(range(self.num_state))).lower(*avals).compile()
        self.compile_s = time.perf_counter() - start

    def on_device(self, batch: list[np.ndarray]):
        import jax
        return [jax.device_put(x, self.device) for x in batch]

    def __call__(self, device_batch):
        results = self.compiled(*self.state, *device_batch)
        self.state = list(results[:self.num_state])
        return results[self.num_state], results[self.num_state + 1]


def time_train_step(step: CompiledTrainStep, batch: list[np.ndarray], runs: int, warmup: int) -> dict:
    """Median, mean and min time (ms) of `runs` steps after `warmup`, batch resident on the device (as after a
    prefetch), and what that means for input: ms and pairs/s per pair of clouds."""
    device_batch = step.on_device(batch)
    for _ in range(warmup):
        _block(step(device_batch))
    times, losses = [], []
    for _ in range(runs):
        start = time.perf_counter()
        loss, _ = step(device_batch)
        loss.block_until_ready()
        times.append(time.perf_counter() - start)
        losses.append(float(loss))
    b = int(batch[0].shape[0])
    median_ms = 1e3 * float(np.median(times))
    return {"median_ms": median_ms, "mean_ms": 1e3 * float(np.mean(times)), "min_ms": 1e3 * float(np.min(times)),
            "ms_per_pair": median_ms / b, "pairs_per_s": 1e3 * b / median_ms, "runs": runs, "warmup": warmup,
            "loss_first": losses[0], "loss_last": losses[-1], "compile_s": step.compile_s}


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


def run_export(export_dir: str, runs: int, warmup: int, precisions=None, points=None, budget_s: float | None = None,
               seed: int = 0, log=print, on_row=None, train_runs: int | None = None) -> dict:
    """Times every artifact of an export directory (optionally only some precisions / point counts): the forward
    artifacts first, then the training steps (`train_runs` steps each, default `runs`), then the reference checks.

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
              "exported_with": manifest.get("exported_with", {}), "latency": [], "train_step": [], "skipped": []}
    rng = np.random.default_rng(seed)
    reference = load_reference(export_dir)
    compiled: dict[str, CompiledForward] = {}  # two cloud sizes of one bucket share an artifact

    def wanted(entry, kind):
        if (precisions and entry["precision"] not in precisions) or (points and entry["points"] not in points):
            return False
        if budget_s is not None and time.perf_counter() - start > budget_s:
            result["skipped"].append({"kind": kind, "points": entry["points"], "precision": entry["precision"],
                                      "batch_size": entry["batch_size"],
                                      "reason": f"time budget of {budget_s:.0f} s spent"})
            return False
        return True

    for entry in manifest["artifacts"]:
        if not wanted(entry, "forward"):
            continue
        if entry["file"] not in compiled:
            compiled[entry["file"]] = CompiledForward(load_forward(export_dir, entry, len(weights)), weights)
        timing = time_forward(compiled[entry["file"]], random_inputs(manifest, entry, rng), runs, warmup)
        row = {"points": entry["points"], "padded_points": entry["padded_points"], "precision": entry["precision"],
               **timing, "reference": check_forward(compiled[entry["file"]], entry, manifest, reference)}
        result["latency"].append(row)
        if on_row is not None:
            on_row(result)
        log(f"{entry['points']} points ({entry['precision']}): median {row['median_ms']:.2f} ms, min "
            f"{row['min_ms']:.2f} ms, host to host {row['median_host_ms']:.2f} ms, compile {row['compile_s']:.1f} s"
            + _describe_check(row["reference"]))
    for entry in manifest.get("train_artifacts", []):
        if not wanted(entry, "train_step"):
            continue
        step = CompiledTrainStep(load_train_step(export_dir, entry, manifest), initial_train_state(weights, manifest))
        check = check_train_step(step, entry, manifest, reference)
        batch = random_inputs(manifest, entry, rng) + random_labels(entry, rng)
        row = {"points": entry["points"], "padded_points": entry["padded_points"], "batch_size": entry["batch_size"],
               "precision": entry["precision"], **time_train_step(step, batch, train_runs or runs, warmup),
               "reference": check}
        del step  # its state (weights and Adam slots) leaves the device before the next artifact
        result["train_step"].append(row)
        if on_row is not None:
            on_row(result)
        log(f"train step {entry['batch_size']} x {entry['points']} points ({entry['precision']}): median "
            f"{row['median_ms']:.2f} ms ({row['ms_per_pair']:.2f} ms per pair), loss {row['loss_first']:.4f} -> "
            f"{row['loss_last']:.4f}, compile {row['compile_s']:.1f} s" + _describe_check(row["reference"]))
    result["total_s"] = time.perf_counter() - start
    return result


def _describe_check(check: dict | None) -> str:
    return "" if check is None else "; vs TensorFlow: " + ", ".join(f"{k} {v:.3g}" for k, v in check.items())


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
        if row.get("kind", "forward") == "forward":
            lines.append(f"| {row['points']:,} | {row['precision']} | skipped: {row['reason']} | | | | | | |")
    checks = [(f"forward {r['points']:,} points {r['precision']}", r.get("reference")) for r in result["latency"]]
    if result.get("train_step") or any(r.get("kind") == "train_step" for r in result["skipped"]):
        lines += ["", "Training step (forward, loss, backward, Adam; batch on the device; state updated in place)", "",
                  "| batch x points | precision | median ms | min ms | ms per pair | pairs/s | loss first -> last |",
                  "|---|---|---:|---:|---:|---:|---|"]
        for row in result.get("train_step", []):
            lines.append(f"| {row['batch_size']} x {row['points']:,} | {row['precision']} | {row['median_ms']:.2f} | "
                         f"{row['min_ms']:.2f} | {row['ms_per_pair']:.2f} | {row['pairs_per_s']:.1f} | "
                         f"{row['loss_first']:.4f} -> {row['loss_last']:.4f} |")
            checks.append((f"train step {row['batch_size']} x {row['points']:,} {row['precision']}",
                           row.get("reference")))
        for row in result["skipped"]:
            if row.get("kind") == "train_step":
                lines.append(f"| {row['batch_size']} x {row['points']:,} | {row['precision']} | skipped: "
                             f"{row['reason']} | | | | |")
    checks = [(name, check) for name, check in checks if check]
    if checks:
        lines += ["", "Against TensorFlow's results on the reference inputs (export machine, CPU, float32):", ""]
        lines += [f"- {name}:{_describe_check(check).split(':', 1)[1]}" for name, check in checks]
    return "\n".join(lines)

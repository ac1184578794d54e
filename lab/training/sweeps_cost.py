"""What more sweeps cost on the CPU, the job of `lab/tools/benchmark_sweeps_cost.py`: for each variant of
`VARIANTS` (the pair, and `model.temporal` stack and delta on 3 and 5 sweeps), in a process of its own
(`lab.children`), the forward as served (the inference plan, `compiled_forward`) and the Trainer's own training step
(the training plan, `bench_steps.train_steps`) on the benchmark cloud of `points` points per sweep, the process's peak
RSS, and optionally the size of the variant's portable XLA forward (CPU and CUDA) at that bucket.
"""
from __future__ import annotations

import os
import tempfile

VARIANTS = {"pair_2": ("data.num_frames=2",),
            "stack_3": ("data.num_frames=3", "model.temporal=stack"),
            "delta_3": ("data.num_frames=3", "model.temporal=delta"),
            "delta_5": ("data.num_frames=5", "model.temporal=delta")}
REFERENCE = "pair_2"  # the variant the ratios divide by


def measure(config: str, sets: list, points: int, forward_runs: int, step_runs: int, export_sizes: bool) -> dict:
    """One variant in this process (a child): see the module docstring. Milliseconds; bytes."""
    import numpy as np
    import tensorflow as tf

    from ff3d_tf.config import load_config
    from ff3d_tf.data.pairs import bucket_size
    from ff3d_tf.model import build_model
    from ff3d_tf.model.forward import compiled_forward
    from lab import bench
    from lab.training import bench_steps

    cfg = load_config(config, sets)
    g, n = cfg.grid, cfg.data.num_frames
    padded = bucket_size(points, cfg.data.point_bucket_base)
    rng = np.random.default_rng(0)
    arrays = bench.random_clouds(rng, points, padded, (g.x_range_m, g.y_range_m, g.z_range_m), 1, n)
    inputs = {k: tf.constant(v) for k, v in arrays.items()}
    model = build_model(cfg)
    forward = compiled_forward(model, cfg.model.jit_compile)
    readings = bench.measure(bench.fetched(lambda: forward(inputs)), forward_runs, warmup=2)
    result = {"sweeps": n, "temporal": cfg.model.temporal, "params": int(model.count_params()),
              "points_per_sweep": points, "padded_points": padded, "plan_inference": model.plan.describe(),
              "forward": bench.summary([r["ms"] for r in readings])}
    labelled = {**inputs, **{k: tf.constant(v) for k, v in bench.random_labels(rng, points, padded).items()}}
    step = bench_steps.train_steps(cfg, {"train": cfg.model.compile}, labelled)["train"]
    bench.elapsed(bench.fetched(step))  # tracing, compilation
    result["train_step"] = bench.summary([r["ms"] for r in bench.measure(bench.fetched(step), step_runs)])
    result["peak_rss_gb"] = bench.proc_status("VmHWM")
    if export_sizes:
        from ff3d_tf.inference.xla_export import export_forward
        with tempfile.TemporaryDirectory() as out:
            manifest = export_forward(cfg, model, [points], out, log=lambda _: None)
            result["xla_forward_bytes"] = {e["file"]: os.path.getsize(os.path.join(out, e["file"]))
                                           for e in manifest["artifacts"]}
    return result


def ratios(results: dict) -> dict:
    """{variant: forward and training-step medians over `REFERENCE`'s} of `measure`'s results in one run."""
    ref = results.get(REFERENCE)
    if not ref or "error" in ref:
        return {}
    return {v: {"forward": r["forward"]["median_ms"] / ref["forward"]["median_ms"],
                "train_step": r["train_step"]["median_ms"] / ref["train_step"]["median_ms"]}
            for v, r in results.items() if "error" not in r}

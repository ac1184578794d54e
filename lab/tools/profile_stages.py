"""Time of each FastFlow3D stage (point encoding, dense stages, head) per compile backend, and optionally the top
ops of one forward or training step from the TensorFlow profiler. Prints a table; --out writes JSON.

python lab/tools/profile_stages.py --config configs/fastflow3d_waymo.yaml --points 32000,1000000 [--trace_dir D]
Stages are timed alone, interleaved round robin (ratios within one run are what to compare on a shared machine):
  encode  rows A-B (pillarize, point encoder, scatter), XLA, graph, and hybrid (compile mode hybrid's layout: each
          cloud's encoding and scatter its own XLA program, the two run at once, `compile.hybrid_encode`);
  dense   rows C-V (convolutions; with the paper head, and its grid part: `FastFlow3D.grid_stages`), XLA and
          graph (oneDNN on CPU);
  decode  rows W-Z (ungrid, head), XLA and graph.
With --trace_dir, each --profile_modes forward and training step at the first point count is traced with
tf.profiler.experimental and the ops that took the most time are listed (op type, total ms, share).
"""
import collections
import glob
import json
import os
import re
import sys
import tempfile

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)
import numpy as np  # noqa: E402

from ff3d_tf import cpu, internals  # noqa: E402
from lab import bench  # noqa: E402


def stage_times(model, inputs: dict, runs: int) -> dict:
    """{stage/backend: median ms} of the three stages on `inputs` (batch 1), each compiled alone."""
    import tensorflow as tf
    from ff3d_tf.model import compile as compile_lib
    fns = {}
    for backend, jit in (("xla", True), ("graph", False)):
        fns[f"encode/{backend}"] = tf.function(lambda x: model.encode_points(x), jit_compile=jit)
        fns[f"dense/{backend}"] = tf.function(lambda b: model.grid_stages(b), jit_compile=jit)
        fns[f"decode/{backend}"] = tf.function(lambda g, e: model.decode_points(g, e), jit_compile=jit)
    fns["encode/hybrid"] = tf.function(lambda x: compile_lib.hybrid_encode(model.encode_points, x, False))
    encoded = fns["encode/xla"](inputs)
    grid = fns["dense/graph"](encoded["bev_features"])
    args = {"encode": (inputs,), "dense": (encoded["bev_features"],), "decode": (grid, encoded)}
    calls = {k: bench.fetched(lambda f=f, a=args[k.split("/")[0]]: f(*a)) for k, f in fns.items()}
    readings = bench.round_robin(calls, runs, warmup=1)
    return {k: bench.summary([r["ms"] for r in rs], ("median",))["median_ms"] for k, rs in readings.items()}


# Host events of the runtime and of tf.data (named like ops, but they contain the ops' time or the input's).
_NOT_OPS = {"Run", "Process", "Start", "Execute", "ExecuteAsyncOnStream", "RunWithBorrowedArgs", "ForeverRepeat",
            "Generator", "Iterator", "MapAndBatch", "Prefetch"}


def top_ops(trace_dir: str, n: int = 12) -> list[tuple[str, float, float]]:
    """(op, total ms, share of the listed events' time) from the profiler's XSpace files under `trace_dir`.

    Host events named "name:Type" are TensorFlow ops (counted by type); XLA's CPU runtime names its thunks after
    the HLO instruction (e.g. "convolution.12", "fusion.3"), counted by instruction kind.
    """
    totals = collections.Counter()
    for path in glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True):
        space = internals.profiler_xspace(path)
        for plane in space.planes:
            names = {k: v.name for k, v in plane.event_metadata.items()}
            for line in plane.lines:
                for event in line.events:
                    name = names.get(event.metadata_id, "")
                    op_type = name.rsplit(":", 1)[-1]
                    if ":" in name and re.fullmatch(r"_?[A-Z][A-Za-z0-9]*", op_type) and op_type not in _NOT_OPS:
                        key = "tf/" + op_type
                    elif "." in name and name.split(".")[-1].isdigit() and " " not in name:
                        key = "xla/" + name.rsplit(".", 1)[0]
                    else:
                        continue
                    totals[key] += event.duration_ps / 1e9
    total = sum(totals.values()) or 1.0
    return [(k, v, v / total) for k, v in totals.most_common(n)]


def main():
    _common.start("inference")  # before TensorFlow is imported
    import tensorflow as tf
    from ff3d_tf.model import build_model
    from lab.training import bench_steps
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--points", default="32000,1000000")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--trace_dir", default=None, help="also trace --profile_modes with the TensorFlow profiler")
    p.add_argument("--profile_modes", default="xla,hybrid")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    cfg = _common.load(args)
    model = build_model(cfg, "none")
    rng = np.random.default_rng(0)
    result = {"cpu": cpu.describe(), "stages": {}, "top_ops": {}}
    for n in [int(v) for v in args.points.split(",")]:
        inputs, _ = bench_steps.example(cfg, rng, n)
        result["stages"][str(n)] = stage_times(model, inputs, args.runs)
        print(f"{n} points: " + ", ".join(f"{k} {v:.0f} ms" for k, v in result["stages"][str(n)].items()),
              flush=True)
    if args.trace_dir:
        n = int(args.points.split(",")[0])
        inputs, _ = bench_steps.example(cfg, rng, n)
        labelled, _ = bench_steps.example(cfg, rng, n, labels=True)
        modes = {m: m for m in args.profile_modes.split(",")}
        steppers = bench_steps.train_steps(cfg, modes, labelled)
        for mode in modes:
            m = build_model(cfg, mode)
            forward = tf.function(lambda x, m=m: m(x), reduce_retracing=True)
            for what, fn in (("forward", lambda: forward(inputs)), ("train_step", steppers[mode])):
                bench.fetch(fn())  # compile outside the trace
                logdir = tempfile.mkdtemp(prefix=f"{mode}_{what}_", dir=args.trace_dir)
                tf.profiler.experimental.start(logdir)
                bench.fetch(fn())
                tf.profiler.experimental.stop()
                ops = top_ops(logdir)
                result["top_ops"][f"{mode}/{what}"] = ops
                print(f"{mode} {what} at {n} points, top ops: " +
                      "; ".join(f"{k} {ms:.0f} ms ({share:.0%})" for k, ms, share in ops), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()

"""TensorFlow's oneDNN operations on against off, per ISA cap: the Trainer's training step and the compiled forward,
each setting in its own child process (TensorFlow reads TF_ENABLE_ONEDNN_OPTS once, at start). JSON out.

python tools/benchmark_onednn.py --out benchmarks/cpu_onednn_avx2.json [--config configs/synthetic_cpu.yaml]
    [--points 20000] [--caps avx2,none] [--steps 5] [--rounds 2]

--caps: `avx2` runs the children with oneDNN and XLA capped to AVX2 (the caps of `ff3d_tf.cpu.EMULATIONS["zen3"]`:
how an AVX2-only CPU such as AMD Zen 3 runs), `none` with this CPU's own ISA. Each round runs every (cap, oneDNN) child once,
in turn, so a change of load hits all alike; the summary is the median over rounds of each child's median step.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

import _common  # noqa: F401

from ff3d_tf import bench, cpu

CAPS = {"avx2": {k: v for k, v in cpu.EMULATIONS["zen3"].items() if k != "TF_ENABLE_ONEDNN_OPTS"}, "none": {}}


def child(config: str, points: int, steps: int) -> dict:
    """In the child: median ms of `steps` training steps and of `steps` forward calls, after a warm-up of each."""
    import numpy as np
    from ff3d_tf import internals
    from ff3d_tf.config import load_config, replace_config
    from ff3d_tf.model import build_model
    from ff3d_tf.model.forward import compiled_forward
    from ff3d_tf.training import bench_steps
    cfg = load_config(config or None, [])
    rng = np.random.default_rng(0)
    labelled, _ = bench_steps.example(cfg, rng, points, labels=True)
    step = bench_steps.train_steps(cfg, {"hybrid": "hybrid"}, labelled)["hybrid"]
    model = build_model(replace_config(cfg, {"train.global_batch_size": 1}), "hybrid")
    forward = compiled_forward(model, cfg.model.jit_compile)
    inputs, _ = bench_steps.example(cfg, rng, points)
    out = {"onednn_enabled": internals.onednn_enabled()}
    for name, fn in (("train_step", step), ("forward", lambda: forward(inputs))):
        rows = bench.measure(bench.fetched(fn), steps, warmup=2)
        out[f"{name}_ms"] = bench.middle([r["ms"] for r in rows])
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="benchmarks/cpu_onednn_avx2.json")
    p.add_argument("--config", default="configs/synthetic_cpu.yaml")
    p.add_argument("--points", type=int, default=20000)
    p.add_argument("--caps", default="avx2,none", help=f"comma-separated, of: {', '.join(CAPS)}")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print("RESULT " + json.dumps(child(args.config, args.points, args.steps)), flush=True)
        return
    variants = [(cap, onednn) for cap in args.caps.split(",") for onednn in ("0", "1")]
    runs = {f"{cap}_onednn_{onednn}": [] for cap, onednn in variants}
    load_start = bench.load_average()
    for round_ in range(args.rounds):
        for cap, onednn in variants:
            env = {**os.environ, **CAPS[cap], "TF_ENABLE_ONEDNN_OPTS": onednn}
            cmd = [sys.executable, os.path.abspath(__file__), "--child", "--config", args.config, "--points",
                   str(args.points), "--steps", str(args.steps)]
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True).stdout
            result = json.loads(out.split("RESULT ", 1)[1])
            runs[f"{cap}_onednn_{onednn}"].append(result)
            print(f"round {round_ + 1} cap {cap} oneDNN {onednn}: {result}", flush=True)
    summary = {name: {k: bench.middle([r[k] for r in rs]) for k in ("train_step_ms", "forward_ms")}
               for name, rs in runs.items()}
    for cap in args.caps.split(","):
        off, on = summary[f"{cap}_onednn_0"], summary[f"{cap}_onednn_1"]
        summary[f"{cap}_onednn_speedup"] = {k: off[k] / on[k] for k in ("train_step_ms", "forward_ms")}
    result = {"cpu": cpu.describe(), "load_average_at_start": load_start, "load_average_at_end": bench.load_average(),
              "config": args.config, "points": args.points, "steps": args.steps, "rounds": args.rounds,
              "how": "medians over rounds of each child's median of --steps after 2 warm-up calls; model.compile "
                     "hybrid, batch 1; caps: " + json.dumps({c: CAPS[c] for c in args.caps.split(",")}),
              "summary": summary, "runs": runs}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=os.path.dirname(os.path.abspath(args.out)), delete=False) as f:
        json.dump(result, f, indent=1)
    os.replace(f.name, args.out)
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()

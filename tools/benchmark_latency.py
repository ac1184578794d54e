"""Forward latency of FastFlow3D vs point count, plus the dense-convolution floor (paper Table 3). JSON out.

python tools/benchmark_latency.py --config configs/fastflow3d_waymo.yaml --out latency.json [--points 32000,...]
Batch 1, warm-up excluded, median and min of --runs runs; peak resident memory during the timed runs (Linux
VmHWM, reset after warm-up so start-up and XLA compilation do not count).
"""
import json
import os
import time

import _common
import numpy as np
import tensorflow as tf

from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.model import build_model


def _cloud(rng, n, cfg):
    g = cfg.grid
    xyz = np.stack([rng.uniform(*g.x_range_m, n), rng.uniform(*g.y_range_m, n), rng.uniform(-2.5, 2.5, n)], -1)
    return xyz.astype(np.float32), rng.uniform(0, 1, (n, 2)).astype(np.float32)


def _rss_gb(field: str) -> float:
    """VmRSS (now) or VmHWM (peak since the last reset) of this process, GB (Linux /proc)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024 / 1e9
    return float("nan")


def _reset_peak_rss() -> bool:
    """Returns freed heap to the OS and resets VmHWM to the current RSS, so the next peak excludes start-up and XLA
    compilation (Linux >= 4.0, glibc). False where that is not possible (the peak then covers the whole process)."""
    import ctypes
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except (OSError, AttributeError):
        return False


def _time(fn, runs, warmup=2):
    for _ in range(warmup):
        tf.nest.map_structure(lambda t: t.numpy(), fn())
    peak_reset = _reset_peak_rss()
    rss_before = _rss_gb("VmRSS")
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        tf.nest.map_structure(lambda t: t.numpy(), fn())
        times.append(time.perf_counter() - t)
    return {"median_ms": 1e3 * float(np.median(times)), "min_ms": 1e3 * float(np.min(times)), "runs": runs,
            # Peak resident memory of the process during the timed runs (start-up and compilation excluded),
            # and what inference added on top of the resident set before them.
            "peak_rss_gb": _rss_gb("VmHWM"), "rss_before_gb": rss_before,
            "peak_increase_gb": _rss_gb("VmHWM") - rss_before, "peak_reset_after_warmup": peak_reset}


def main():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--points", default="32000,100000,255000,1000000")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--out", default="latency.json")
    args = p.parse_args()
    cfg = _common.load(args)
    model = build_model(cfg)
    framework_baseline_gb = _rss_gb("VmRSS")  # TensorFlow imported, model variables created
    jit = cfg.model.jit_compile
    forward = tf.function(lambda x: model(x, training=False), jit_compile=jit)
    rng = np.random.default_rng(0)
    results = {"device": (tf.config.list_physical_devices("GPU") or ["cpu"])[0].__repr__(),
               "grid": [cfg.grid.num_pillars_x, cfg.grid.num_pillars_y], "jit_compile": jit,
               "mixed_precision": cfg.model.mixed_precision, "params": model.count_params(),
               "framework_baseline_rss_gb": framework_baseline_gb, "latency": {}}
    # Conv floor: the encoder (both frames stacked) + decoder on an already-built grid.
    h, w, c = cfg.grid.num_pillars_y, cfg.grid.num_pillars_x, cfg.model.point_feature_dim
    bev = tf.cast(tf.constant(rng.uniform(0, 1, (2, h, w, c)).astype(np.float32)), model.conv_v.compute_dtype)

    def convs(x):
        skips = [x]
        for stage in model.encoder_stages:
            for block in stage:
                x = block(x)
            skips.append(x)

        def both(t):
            return tf.concat([t[:1], t[1:]], -1)
        y = model.upsample_skips[0]([both(skips[3]), both(skips[2])])
        y = model.upsample_skips[1]([y, both(skips[1])])
        y = model.upsample_skips[2]([y, both(skips[0])])
        return model.conv_v(y)
    for n in [int(v) for v in args.points.split(",")]:
        padded = bucket_size(n, cfg.data.point_bucket_base)
        p0, f0 = _cloud(rng, n, cfg)
        p1, f1 = _cloud(rng, n, cfg)
        pad = [[0, padded - n], [0, 0]]
        inputs = {"points_xyz_t0": tf.constant(np.pad(p0, pad)[None]),
                  "point_features_t0": tf.constant(np.pad(f0, pad)[None]),
                  "point_mask_t0": tf.sequence_mask([n], padded),
                  "points_xyz_tm1_in_t0": tf.constant(np.pad(p1, pad)[None]),
                  "point_features_tm1": tf.constant(np.pad(f1, pad)[None]),
                  "point_mask_tm1": tf.sequence_mask([n], padded)}
        r = _time(lambda: forward(inputs), args.runs)
        r["padded_points"] = padded
        if tf.config.list_physical_devices("GPU"):
            r["gpu_peak_gb"] = tf.config.experimental.get_memory_info("GPU:0")["peak"] / 1e9
        results["latency"][str(n)] = r
        print(f"{n} points: median {r['median_ms']:.1f} ms, min {r['min_ms']:.1f} ms, peak RSS during inference "
              f"{r['peak_rss_gb']:.2f} GB (+{r['peak_increase_gb']:.2f} GB over {r['rss_before_gb']:.2f})",
              flush=True)
    # The conv floor runs last, so that its buffers do not count in the point runs' peak memory.
    conv_fn = tf.function(convs, jit_compile=jit)
    results["conv_floor"] = _time(lambda: conv_fn(bev), args.runs)
    print(f"conv floor: {results['conv_floor']['median_ms']:.1f} ms", flush=True)
    lat = results["latency"]
    keys = sorted(lat, key=int)
    results["ratio_max_over_min_points"] = lat[keys[-1]]["median_ms"] / lat[keys[0]]["median_ms"]
    results["ratio_min_points_over_conv_floor"] = lat[keys[0]]["median_ms"] / results["conv_floor"]["median_ms"]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(json.dumps({k: v for k, v in results.items() if k.startswith("ratio")}))


if __name__ == "__main__":
    main()

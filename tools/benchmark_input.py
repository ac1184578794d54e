"""Training input in pairs/s per core: decoding WOD frames on the fly vs decode-once pair records. JSON out.

python tools/benchmark_input.py --out benchmarks/input_cpu.json [--densities wod,synthetic] [--cores 1,2]
python tools/benchmark_input.py --av2 --out benchmarks/input_cpu.json [--cores 1,2]   (merged in as key "av2")
python tools/benchmark_input.py --official --data_dir D --out O   (graph reader vs the official frame_utils)

For each density (synthetic WOD segments: `wod` ~177K points per frame over five lidars, first return, as WOD;
`synthetic` the embedded default's full size, about twice that), in a child process pinned to 1, 2, ... cores
(CPU affinity, TensorFlow and tf.data thread pools of that size), after the first batch:
  stages   where a decoded pair's CPU time goes: TFRecord read alone, + in-graph decode of each frame (zlib, range
           image to points, flow), + pairing (ego motion, studies), + batching and bucket padding (the training
           input's `training_dataset`), cumulative, as pairs/s (frames/s for the first two);
  records  the same training input read from pair records (`tools/write_pair_records.py`), exact and compact.
Disk: bytes per pair of each record kind, and the WOD training split's size at that rate (798 segments of ~198 pairs;
Sun et al., CVPR 2020).

--av2: where Argoverse 2 labels are computed, on synthetic AV2 logs (`ff3d_tf.data.synthetic.av2`, `--av2_points`
per sweep: 100K as the sample log's 99,229 and 99,466 over two 32-beam lidars; the module's default, 6,000, is a test
size), in the same pinned children:
  labels_in_pipeline  labelling on the fly: `labels.av2.challenge_pair` per pair (both sweeps' feather files, poses,
                      cuboids, box flow, categories, ground raster mask) in the trainer's tf.data map (py_function,
                      parallel), as pairs/s; studies, shuffling and batching not included (they only lower it);
  write_<precision>   the records job (`labels.av2.write_log_records`, one log per worker, `cores` workers), pairs/s
                      and bytes per pair on disk;
  records_<precision> the training input's `training_dataset` reading those records (as `records` above), after untimed
                      warm-up readings (a process's first ones run up to 2-3x slower: fresh memory).
The result goes into `--out` as its key "av2"; the file's other keys are kept.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

import _common

from ff3d_tf import bench, children

DENSITY_LIDAR_SCALE = {"wod": 0.715, "synthetic": 1.0}  # range-image scale; points grow with its square
WOD_TRAIN_PAIRS = 798 * 198
AV2_TRAIN_PAIRS = 700 * 149  # 700 training logs of 15 s at 10 Hz (Wilson et al., NeurIPS Datasets and Benchmarks 2021)


def _args(argv=None):
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--densities", default="wod,synthetic")
    p.add_argument("--cores", default="1,2")
    p.add_argument("--frames_per_segment", type=int, default=6)
    p.add_argument("--segments", type=int, default=2)
    p.add_argument("--batches", type=int, default=8, help="batches of train.global_batch_size timed per reading")
    p.add_argument("--out", default="benchmarks/input_cpu.json")
    p.add_argument("--official", action="store_true", help="graph reader vs official frame_utils (needs --data_dir)")
    p.add_argument("--data_dir", default=None)
    p.add_argument("--av2", action="store_true", help="Argoverse 2: labels in the input pipeline vs pair records")
    p.add_argument("--av2_logs", type=int, default=4)
    p.add_argument("--av2_sweeps", type=int, default=5, help="sweeps per synthetic AV2 log")
    p.add_argument("--av2_points", type=int, default=100_000, help="points per synthetic AV2 sweep")
    p.add_argument("--frames", type=int, default=10, help="--official: frames read")
    p.add_argument("--child", default="", help=argparse.SUPPRESS)  # internal: "<cores>:<json args>"
    return p.parse_args(argv)


def _rate(ds, count: int, per_item: int = 1) -> dict:
    """Items/s of a dataset after its first element (start-up and tracing excluded)."""
    it = iter(ds)
    _, first_s = bench.elapsed(lambda: next(it))
    _, seconds = bench.elapsed(lambda: [next(it) for _ in range(count)])
    return {"per_s": count * per_item / seconds, "timed": count * per_item, "first_s": first_s}


def _options(cores: int):
    import tensorflow as tf
    options = tf.data.Options()
    options.threading.private_threadpool_size = cores
    options.threading.max_intra_op_parallelism = 1
    return options


def _child(args, cores: int, job: dict) -> dict:
    if "av2_logs" in job:
        return _child_av2(args, cores, job)
    import tensorflow as tf
    from ff3d_tf.config import replace_config
    from ff3d_tf.data import pairs
    from ff3d_tf.data.wod import wod_decode
    from ff3d_tf.training.input import training_dataset
    cfg = _common.load(args)
    options = _options(cores)
    batch = cfg.train.global_batch_size
    out = {}
    segments = job["segments"]
    frames = tf.data.Dataset.from_tensor_slices(segments).interleave(tf.data.TFRecordDataset).repeat()
    out["read_frames"] = _rate(frames.with_options(options), 4 * args.batches * batch)
    decoder = wod_decode.traced_decoder(pairs.decode_options(cfg))
    decoded = frames.map(lambda r: decoder(r, tf.constant("bench"))["points_xyz"],
                         num_parallel_calls=tf.data.AUTOTUNE)
    out["decode_frames"] = _rate(decoded.with_options(options), args.batches * batch)
    out["decode_and_pair"] = _rate(pairs.pair_dataset(segments, cfg).repeat().with_options(options),
                                   args.batches * batch)
    out["decode_pair_batch"] = _rate(training_dataset(segments, cfg, batch).with_options(options), args.batches,
                                     batch)
    for kind, files in job["records"].items():
        rcfg = replace_config(cfg, {"data.source": "pair_records"})
        out[f"records_{kind}"] = _rate(training_dataset(files, rcfg, batch).with_options(options), args.batches,
                                       batch)
    return out


def _child_av2(args, cores: int, job: dict) -> dict:
    """`--av2` readings on `cores` cores: labelling in the input pipeline, the records job, reading its records."""
    import glob
    from concurrent.futures import ThreadPoolExecutor
    import tensorflow as tf
    from ff3d_tf.config import replace_config
    from ff3d_tf.data import pair_records
    from ff3d_tf.labels import av2
    from ff3d_tf.training.input import training_dataset
    cfg = _common.load(args)
    options, batch, logs = _options(cores), cfg.train.global_batch_size, job["av2_logs"]
    tasks = [(log, i) for log in logs for i in range(job["sweeps"] - 1)]

    for task in tasks[:2]:
        av2.challenge_pair(*task, cfg)  # warm-up (first eager calls), untimed
    out, files = {}, {}
    for precision in ("exact", "compact"):
        out_dir = os.path.join(job["out_dir"], f"{cores}_cores_{precision}")
        manifest = av2.records_manifest(cfg, precision)
        pair_records.write_manifest(out_dir, manifest)
        with ThreadPoolExecutor(cores) as pool:  # a Beam worker per core, one log per element
            counts, seconds = bench.elapsed(
                lambda: list(pool.map(lambda log: av2.write_log_records(log, out_dir, cfg, manifest), logs)))
        n_pairs, n_bytes = sum(c["pairs"] for c in counts), sum(c["bytes"] for c in counts)
        out[f"write_{precision}"] = {"per_s": n_pairs / seconds, "timed": n_pairs, "bytes_per_pair": n_bytes / n_pairs,
                                     "av2_train_split_tb": n_bytes / n_pairs * AV2_TRAIN_PAIRS / 1e12}
        files[precision] = sorted(glob.glob(os.path.join(out_dir, "*" + pair_records.FILE_SUFFIX)))
    rcfg = replace_config(cfg, {"data.source": "pair_records"})
    reading = lambda p: training_dataset(files[p], rcfg, batch).with_options(options)  # noqa: E731

    def label(k):
        return av2.challenge_pair(*tasks[int(k) % len(tasks)], cfg)["num_points_t0"]
    labelled = tf.data.Dataset.range(2 ** 40).map(lambda k: tf.py_function(label, [k], tf.int32),
                                                 num_parallel_calls=tf.data.AUTOTUNE)
    out["labels_in_pipeline"] = _rate(labelled.with_options(options), job["pairs_timed"])
    # Warm-up, untimed: a process's first readings of 100K-point pairs run up to 2-3x slower than its later ones
    # (fresh memory: page faults until the allocator reuses it), which a long training does not see.
    for precision in ("exact", "compact"):
        _rate(reading(precision), 2, batch)
    for precision in ("exact", "compact"):
        out[f"records_{precision}"] = _rate(reading(precision), args.batches, batch)
    return out


def _av2(args, cores: list[int], argv) -> dict:
    """The `--av2` part: synthetic AV2 logs, then `_child_av2` pinned to each core count."""
    from ff3d_tf.data.av2 import argoverse2
    from ff3d_tf.data.synthetic import av2 as synthetic_av2
    cfg = _common.load(args)
    result = {"command": " ".join(["python tools/benchmark_input.py"] + list(sys.argv[1:] if argv is None else argv)),
              "config": args.config, "overrides": args.set, "batch_size": cfg.train.global_batch_size,
              "cpus_available": len(os.sched_getaffinity(0)), "load_average_start": bench.load_average()}
    with tempfile.TemporaryDirectory() as tmp:
        logs = synthetic_av2.write_synthetic_split(tmp, args.av2_logs, "train", args.av2_sweeps, seed=17,
                                                   points_per_sweep=args.av2_points, progress=lambda *a: None)
        stamps = argoverse2.sweep_timestamps(logs[0])
        result.update({"logs": len(logs), "sweeps_per_log": args.av2_sweeps, "pairs": len(logs) * (args.av2_sweeps - 1),
                       "points_per_sweep": len(argoverse2.read_sweep(logs[0], stamps[0])["points_xyz"])})
        job = {"av2_logs": logs, "sweeps": args.av2_sweeps, "pairs_timed": 2 * result["pairs"], "out_dir": tmp}
        runs = {str(c): _in_child(args, c, job) for c in cores}
    result["runs"] = runs
    result["per_core_per_s"] = {c: {k: v["per_s"] / int(c) for k, v in r.items()} for c, r in runs.items()}
    result["bytes_per_pair"] = {p: runs[str(cores[0])][f"write_{p}"]["bytes_per_pair"] for p in ("exact", "compact")}
    result["records_over_labels_in_pipeline"] = {
        c: {p: r[f"records_{p}"] / r["labels_in_pipeline"] for p in ("exact", "compact")}
        for c, r in result["per_core_per_s"].items()}
    result["load_average_end"] = bench.load_average()
    print(json.dumps({k: result[k] for k in ("points_per_sweep", "per_core_per_s", "bytes_per_pair",
                                             "records_over_labels_in_pipeline")}, indent=1), flush=True)
    return result


def _in_child(args, cores: int, job: dict) -> dict:
    """`_child` in a fresh process pinned to `cores` CPUs (thread pools cannot shrink once started)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "result.json")
        cmd = [sys.executable, os.path.abspath(__file__), "--child", f"{cores}:{json.dumps(job)}", "--out", out,
               "--batches", str(args.batches), "--config", args.config or ""]
        cmd += [a for s in args.set for a in ("--set", s)]
        env = {**os.environ, "TF_NUM_INTEROP_THREADS": str(cores), "TF_NUM_INTRAOP_THREADS": str(cores)}
        run = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if run.returncode != 0:
            sys.exit(f"measurement on {cores} cores failed:\n{run.stderr[-3000:]}")
        with open(out) as f:
            return json.load(f)


def _prepare(args, density: str, tmp: str) -> dict:
    """Synthetic segments of one density and their pair records (exact, compact); sizes and points."""
    import tensorflow as tf
    from ff3d_tf.data import pair_records, pairs
    from ff3d_tf.data.synthetic import wod as synthetic
    from ff3d_tf.data.wod import write_records
    cfg = _common.load(args)
    seg_dir = os.path.join(tmp, density, "segments")
    os.makedirs(seg_dir)
    segments = []
    for k in range(args.segments):
        path = os.path.join(seg_dir, f"segment-bench-{k:03d}.tfrecord")
        synthetic.write_segment(path, synthetic.SegmentSpec(seed=300 + k, num_frames=args.frames_per_segment,
                                                            lidar_scale=DENSITY_LIDAR_SCALE[density]))
        segments.append(path)
    job = {"segments": segments, "records": {}}
    sizes = {"frame_record_bytes": sum(os.path.getsize(s) for s in segments) / (len(segments) *
                                                                               args.frames_per_segment)}
    first = next(iter(pairs.pair_dataset(segments[:1], cfg)))
    sizes["points_per_frame"] = int(first["num_points_t0"])
    for precision in ("exact", "compact"):
        out_dir = os.path.join(tmp, density, f"records_{precision}")
        manifest = write_records.wod_manifest(cfg, precision)
        pair_records.write_manifest(out_dir, manifest)
        counts = [write_records.write_segment(s, out_dir, cfg, manifest) for s in segments]
        n_pairs, n_bytes = sum(c["pairs"] for c in counts), sum(c["bytes"] for c in counts)
        sizes[f"{precision}_bytes_per_pair"] = n_bytes / n_pairs
        sizes[f"{precision}_wod_train_split_tb"] = n_bytes / n_pairs * WOD_TRAIN_PAIRS / 1e12
        sizes[f"{precision}_write_pairs_per_s"] = n_pairs / sum(c["seconds"] for c in counts)
        job["records"][precision] = sorted(tf.io.gfile.glob(os.path.join(out_dir, "*" + pair_records.FILE_SUFFIX)))
    return job, sizes


def _official(args) -> dict:
    """Frames/s of the graph reader (eager and tf.data) vs the official Python frame_utils path, same records."""
    import tensorflow as tf
    from waymo_open_dataset import dataset_pb2
    from waymo_open_dataset.utils import frame_utils
    from ff3d_tf.data.wod import waymo, wod_decode
    from ff3d_tf.data.pairs import list_segment_files
    files = list_segment_files(args.data_dir)
    records = [r for _, r in waymo.iterate_records(files[0])][: args.frames]
    waymo.decode_frame(records[0])  # trace once
    n_ours, eager_s = bench.elapsed(lambda: sum(len(waymo.decode_frame(r)["points_xyz"]) for r in records))
    ds = tf.data.Dataset.from_tensor_slices(records).map(
        lambda r: wod_decode.decode_frame_tensors(r, tf.constant("bench"), wod_decode.DecodeOptions())["points_xyz"],
        num_parallel_calls=tf.data.AUTOTUNE)
    next(iter(ds))  # trace and warm up
    n_tfdata, tfdata_s = bench.elapsed(lambda: sum(1 for _ in ds))

    def official_points():
        n = 0
        for r in records:
            frame = dataset_pb2.Frame.FromString(r)
            ri, cp, _, top_pose = frame_utils.parse_range_image_and_camera_projection(frame)
            pts, _ = frame_utils.convert_range_image_to_point_cloud(frame, ri, cp, top_pose)
            n += sum(len(x) for x in pts)
        return n
    n_ref, official_s = bench.elapsed(official_points)
    assert n_ref == n_ours and n_tfdata == len(records), (n_ref, n_ours, n_tfdata)
    n = len(records)
    return {"frames": n, "points_per_frame": n_ours / n, "official_fps": n / official_s,
            "graph_eager_fps": n / eager_s, "graph_tfdata_fps": n / tfdata_s,
            "speedup_eager": official_s / eager_s, "speedup_tfdata": official_s / tfdata_s}


def main(argv=None):
    args = _args(argv)
    if args.child:
        cores, job = args.child.split(":", 1)
        children.pin_cores(int(cores))
        result = _child(args, int(cores), json.loads(job))
    elif args.av2:
        av2 = _av2(args, [int(c) for c in args.cores.split(",")], argv)
        result = {}
        if os.path.exists(args.out):
            with open(args.out) as f:
                result = json.load(f)
        result["av2"] = av2
    elif args.official:
        if not args.data_dir:
            sys.exit("--official needs --data_dir")
        result = _official(args)
    else:
        cores = [int(c) for c in args.cores.split(",")]
        result = {"config": args.config, "overrides": args.set, "batch_size": _common.load(args).train.global_batch_size,
                  "cpus_available": len(os.sched_getaffinity(0)), "load_average_start": bench.load_average(),
                  "densities": {}}
        with tempfile.TemporaryDirectory() as tmp:
            for density in args.densities.split(","):
                job, sizes = _prepare(args, density, tmp)
                runs = {str(c): _in_child(args, c, job) for c in cores}
                per_core = {c: {k: v["per_s"] / int(c) for k, v in r.items()} for c, r in runs.items()}
                result["densities"][density] = {"sizes": sizes, "runs": runs, "per_core_per_s": per_core}
                print(json.dumps({density: {"sizes": sizes, "per_core_per_s": per_core}}, indent=1), flush=True)
        result["load_average_end"] = bench.load_average()
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()

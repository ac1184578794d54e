"""Rates of the training input, each read in a fresh process pinned to N cores (`lab.children.run_child`: CPU
affinity and TensorFlow's thread pools of that size; here also tf.data's private pool), after the dataset's first
element so that start-up and tracing are not counted (lab/tools/benchmark_input.py, lab/tools/benchmark_training.py).

`input_benchmark`, per density of synthetic WOD segments (a range-image scale), per core count:
  stages   where a decoded pair's CPU time goes, cumulative: TFRecord read alone ("read_frames", frames/s), + the
           in-graph decode of each frame ("decode_frames", frames/s), + pairing ("decode_and_pair"), + batching and
           bucket padding, the training input's `training_dataset` ("decode_pair_batch"), all pairs/s;
  records  the same training input read from pair records of each precision ("records_exact", "records_compact");
and the records' bytes per pair and write rate, and the WOD training split's size at that rate.

`av2_input_benchmark`, on synthetic Argoverse 2 logs, per core count: labels made in the input pipeline (a labeller's
`challenge_pair` per pair in a parallel tf.data map; shuffling and batching not included) against the records job
(`write_<precision>`: one log per worker, one worker per core) and the training input reading its records
(`records_<precision>`, after untimed warm-up readings: a process's first readings run slower, on fresh memory).
The labeller is a module named by the caller (ff3d_tf.labels.av2): a training module does not import labels.

`input_pairs_per_s` (the training input alone) and `count_decodes` (decodes per epoch of `pairs.pair_dataset`, one per
frame although a frame is in two pairs) are what `bench_steps.training_benchmark` reads of the input.

Functions named `*_child` run in those processes: JSON arguments (the config file, its overrides, file paths), a dict
back that holds, under "cpus", the CPUs the process ran on.
"""
from __future__ import annotations

import glob
import importlib
import json
import os
import tempfile
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence

import tensorflow as tf

from ff3d_tf import cpu
from ff3d_tf.config import ExperimentConfig, load_config, replace_config
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.synthetic import av2 as synthetic_av2
from ff3d_tf.data.synthetic import wod as synthetic_wod
from ff3d_tf.data.wod import waymo, wod_decode, write_records
from ff3d_tf.training.input import training_dataset
from lab import bench, children

DENSITY_LIDAR_SCALE = {"wod": 0.715, "synthetic": 1.0}  # synthetic range-image scale; points grow with its square
WOD_TRAIN_PAIRS = 798 * 198  # 798 training segments of ~198 pairs (Sun et al., CVPR 2020)
AV2_TRAIN_PAIRS = 700 * 149  # 700 training logs of 15 s at 10 Hz (Wilson et al., NeurIPS Datasets and Benchmarks 2021)
PRECISIONS = ("exact", "compact")
MODULE = __name__


def check_core_counts(cores: Sequence[int]) -> None:
    """Raises ValueError, before any work, when a core count is not between 1 and the CPUs this process may use."""
    available = len(os.sched_getaffinity(0))
    wrong = [n for n in cores if not 1 <= n <= available]
    if wrong or not cores:
        raise ValueError(f"core counts {list(cores)} asked; each must be 1 to {available}, the CPUs this process "
                         "may use")


def header(config: str | None, overrides: Sequence[str], cfg: ExperimentConfig) -> dict:
    """The fields every result starts with: the config file and overrides as given, the batch size, the CPUs."""
    return {"config": config, "overrides": list(overrides), "batch_size": cfg.train.global_batch_size,
            "cpus_available": len(os.sched_getaffinity(0)), "cpu": cpu.describe()}


def child_config(config: str | None) -> str | None:
    """`config` as a child (started in the repository root) finds it: an absolute path."""
    return os.path.abspath(config) if config and "://" not in config else config


def per_core(function: str, kwargs: dict, cores: Sequence[int], what: str) -> dict[str, dict]:
    """{str(n): `function(**kwargs, cores=n)`} for each n of `cores`, each in a fresh process pinned to n cores;
    a failure raises `children.ChildError` naming `what` and n."""
    return {str(n): children.run_child(function, {**kwargs, "cores": n}, cores=n, what=f"{what} on {n} core(s)")
            for n in cores}


def per_core_per_s(runs: dict[str, dict]) -> dict[str, dict]:
    """{cores: {reading: its "per_s" divided by cores}} of `per_core`'s readings (other fields skipped)."""
    return {c: {k: v["per_s"] / int(c) for k, v in r.items() if isinstance(v, dict) and "per_s" in v}
            for c, r in runs.items()}


def pinned_options(cores: int) -> tf.data.Options:
    """tf.data options of a reading on `cores` cores: a private pool of `cores` threads, no intra-op parallelism."""
    options = tf.data.Options()
    options.threading.private_threadpool_size = cores
    options.threading.max_intra_op_parallelism = 1
    return options


def _after_first(ds: tf.data.Dataset, count: int, read: Callable = lambda element: None) -> tuple[float, float, list]:
    """(seconds to `ds`'s first element, seconds for the `count` next ones, `read` of each of those)."""
    it = iter(ds)
    _, first_s = bench.elapsed(lambda: next(it))
    values, seconds = bench.elapsed(lambda: [read(next(it)) for _ in range(count)])
    return first_s, seconds, values


def rate(ds: tf.data.Dataset, count: int, items_per_element: int = 1) -> dict:
    """{"per_s": items/s over the `count` elements after the first, "timed": items timed, "first_s": seconds to the
    first element}; an element holds `items_per_element` items (a batch, its pairs)."""
    first_s, seconds, _ = _after_first(ds, count)
    return {"per_s": count * items_per_element / seconds, "timed": count * items_per_element, "first_s": first_s}


def records_input(files: list[str], cfg: ExperimentConfig, cores: int) -> tf.data.Dataset:
    """The training input of `cfg` reading the pair records `files`, with `pinned_options(cores)`."""
    rcfg = replace_config(cfg, {"data.source": "pair_records"})
    return training_dataset(files, rcfg, cfg.train.global_batch_size).with_options(pinned_options(cores))


def input_pairs_per_s(files: list[str], cfg: ExperimentConfig, cores: int, batches: int) -> dict:
    """Pairs/s of the training input of `files` over `batches` batches after the first, with tf.data's own pool of
    `cores` threads, and the mean t0 point count of those batches."""
    batch = cfg.train.global_batch_size
    ds = training_dataset(files, cfg, batch).with_options(pinned_options(cores))
    first_s, seconds, points = _after_first(
        ds, batches, lambda b: float(tf.reduce_mean(tf.cast(b["num_points_t0"], tf.float32))))
    return {"cores": cores, "pairs_per_s": batches * batch / seconds, "pairs_timed": batches * batch,
            "first_batch_s": first_s, "mean_points_t0": sum(points) / len(points)}


def training_input_child(config: str | None, overrides: list[str], files: list[str], cores: int, batches: int) -> dict:
    """`input_pairs_per_s` of `files` under the config file `config` with `overrides`, and "cpus"."""
    return {**input_pairs_per_s(files, load_config(config, overrides), cores, batches),
            "cpus": children.placement()["cpus"]}


def count_decodes(files: list[str], cfg: ExperimentConfig) -> dict:
    """Frames decoded during one pass over `pair_dataset` (a counter in the decoder) vs frames and pairs."""
    from unittest import mock
    decodes = tf.Variable(0, dtype=tf.int64, trainable=False)
    make_decoder = wod_decode.traced_decoder  # the one decoder every frame goes through (traced once per process)

    def counting_decoder(options):
        decode = make_decoder(options)

        def counted(record, source):
            with tf.control_dependencies([decodes.assign_add(1)]):
                return decode(record, source)
        return counted

    frames = sum(1 for path in files for _ in waymo.iterate_records(path))
    with mock.patch.object(wod_decode, "traced_decoder", counting_decoder):
        num_pairs = sum(1 for _ in pairs.pair_dataset(files, cfg))
    return {"frames": frames, "pairs": num_pairs, "decodes": int(decodes.numpy()),
            "decodes_if_each_pair_decoded_both_frames": 2 * num_pairs,
            "decode_once_per_frame": int(decodes.numpy()) == frames}


def write_synthetic_segments(out_dir: str, count: int, frames_per_segment: int, lidar_scale: float,
                             first_seed: int) -> list[str]:
    """Paths of `count` synthetic WOD segments written into `out_dir` (seeds first_seed, first_seed + 1, ...)."""
    os.makedirs(out_dir, exist_ok=True)
    paths = []
    for k in range(count):
        path = os.path.join(out_dir, f"segment-bench-{k:03d}.tfrecord")
        synthetic_wod.write_segment(path, synthetic_wod.SegmentSpec(seed=first_seed + k, num_frames=frames_per_segment,
                                                                    lidar_scale=lidar_scale))
        paths.append(path)
    return paths


def _pairs_and_bytes(counts: list[dict]) -> tuple[int, int]:
    return sum(c["pairs"] for c in counts), sum(c["bytes"] for c in counts)


def _record_files(out_dir: str) -> list[str]:
    return sorted(glob.glob(os.path.join(out_dir, "*" + pair_records.FILE_SUFFIX)))


def wod_segments_and_records(cfg: ExperimentConfig, out_dir: str, lidar_scale: float, segments: int,
                             frames_per_segment: int) -> tuple[dict, dict]:
    """Synthetic segments at `lidar_scale` and their pair records of each precision, under `out_dir`:
    ({"segments": paths, "records": {precision: paths}}, sizes: bytes per frame record, points per frame, and per
    precision bytes per pair, the WOD training split in TB at that size, pairs/s written)."""
    paths = write_synthetic_segments(os.path.join(out_dir, "segments"), segments, frames_per_segment, lidar_scale,
                                     first_seed=300)
    files = {"segments": paths, "records": {}}
    sizes = {"frame_record_bytes": sum(os.path.getsize(s) for s in paths) / (len(paths) * frames_per_segment),
             "points_per_frame": int(next(iter(pairs.pair_dataset(paths[:1], cfg)))["num_points_t0"])}
    for precision in PRECISIONS:
        records_dir = os.path.join(out_dir, f"records_{precision}")
        manifest = write_records.wod_manifest(cfg, precision)
        pair_records.write_manifest(records_dir, manifest)
        counts = [write_records.write_segment(s, records_dir, cfg, manifest) for s in paths]
        n_pairs, n_bytes = _pairs_and_bytes(counts)
        sizes[f"{precision}_bytes_per_pair"] = n_bytes / n_pairs
        sizes[f"{precision}_wod_train_split_tb"] = n_bytes / n_pairs * WOD_TRAIN_PAIRS / 1e12
        sizes[f"{precision}_write_pairs_per_s"] = n_pairs / sum(c["seconds"] for c in counts)
        files["records"][precision] = _record_files(records_dir)
    return files, sizes


def wod_stages_child(config: str | None, overrides: list[str], cores: int, segments: list[str],
                     records: dict[str, list[str]], batches: int) -> dict:
    """The stages and records readings (module docstring) of `segments` and `records` on `cores` cores, and "cpus".
    Timed after the first element: as many frames as 4 x `batches` batches hold pairs read, as many as `batches`
    batches hold decoded and paired, `batches` batches of each training input."""
    cfg = load_config(config, overrides)
    options, batch = pinned_options(cores), cfg.train.global_batch_size
    frames = tf.data.Dataset.from_tensor_slices(segments).interleave(tf.data.TFRecordDataset).repeat()
    decoder = wod_decode.traced_decoder(pairs.decode_options(cfg))
    decoded = frames.map(lambda r: decoder(r, tf.constant("bench"))["points_xyz"], num_parallel_calls=tf.data.AUTOTUNE)
    out = {"read_frames": rate(frames.with_options(options), 4 * batches * batch),
           "decode_frames": rate(decoded.with_options(options), batches * batch),
           "decode_and_pair": rate(pairs.pair_dataset(segments, cfg).repeat().with_options(options), batches * batch),
           "decode_pair_batch": rate(training_dataset(segments, cfg, batch).with_options(options), batches, batch)}
    for precision, files in records.items():
        out[f"records_{precision}"] = rate(records_input(files, cfg, cores), batches, batch)
    return {**out, "cpus": children.placement()["cpus"]}


def input_benchmark(config: str | None, overrides: Sequence[str], densities: dict[str, float], cores: Sequence[int],
                    segments: int = 2, frames_per_segment: int = 6, batches: int = 8,
                    progress: Callable[[str], None] = print) -> dict:
    """The stages and records readings (module docstring) of each {density name: lidar scale} of `densities` on each
    core count of `cores`; `progress` gets each density's sizes and per-core rates as JSON."""
    check_core_counts(cores)
    cfg = load_config(config, overrides)
    result = {**header(config, overrides, cfg), "load_average_start": bench.load_average(), "densities": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for density, lidar_scale in densities.items():
            files, sizes = wod_segments_and_records(cfg, os.path.join(tmp, density), lidar_scale, segments,
                                                    frames_per_segment)
            runs = per_core(f"{MODULE}:wod_stages_child", {"config": child_config(config), "overrides": list(overrides),
                                                           **files, "batches": batches}, cores, f"input ({density})")
            rates = per_core_per_s(runs)
            result["densities"][density] = {"sizes": sizes, "runs": runs, "per_core_per_s": rates}
            progress(json.dumps({density: {"sizes": sizes, "per_core_per_s": rates}}, indent=1))
    result["load_average_end"] = bench.load_average()
    return result


def av2_child(config: str | None, overrides: list[str], cores: int, logs: list[str], sweeps: int, pairs_timed: int,
              out_dir: str, batches: int, labeller: str) -> dict:
    """The Argoverse 2 readings (module docstring) of `logs` (`sweeps` sweeps each) on `cores` cores, records
    written under `out_dir`, and "cpus". `labeller`: the module with `challenge_pair(log, index, cfg)`,
    `records_manifest(cfg, precision)` and `write_log_records(log, out_dir, cfg, manifest)`."""
    labels = importlib.import_module(labeller)
    cfg = load_config(config, overrides)
    batch = cfg.train.global_batch_size
    tasks = [(log, i) for log in logs for i in range(sweeps - 1)]
    for task in tasks[:2]:
        labels.challenge_pair(*task, cfg)  # warm-up (first eager calls), untimed
    out, files = {}, {}
    for precision in PRECISIONS:
        records_dir = os.path.join(out_dir, f"{cores}_cores_{precision}")
        manifest = labels.records_manifest(cfg, precision)
        pair_records.write_manifest(records_dir, manifest)
        with ThreadPoolExecutor(cores) as pool:  # a Beam worker per core, one log per element
            counts, seconds = bench.elapsed(
                lambda: list(pool.map(lambda log: labels.write_log_records(log, records_dir, cfg, manifest), logs)))
        n_pairs, n_bytes = _pairs_and_bytes(counts)
        out[f"write_{precision}"] = {"per_s": n_pairs / seconds, "timed": n_pairs, "bytes_per_pair": n_bytes / n_pairs,
                                     "av2_train_split_tb": n_bytes / n_pairs * AV2_TRAIN_PAIRS / 1e12}
        files[precision] = _record_files(records_dir)

    def points_of_pair(k):
        return labels.challenge_pair(*tasks[int(k) % len(tasks)], cfg)["num_points_t0"]
    labelled = tf.data.Dataset.range(2 ** 40).map(lambda k: tf.py_function(points_of_pair, [k], tf.int32),
                                                 num_parallel_calls=tf.data.AUTOTUNE)
    out["labels_in_pipeline"] = rate(labelled.with_options(pinned_options(cores)), pairs_timed)
    for precision in PRECISIONS:  # warm-up, untimed
        rate(records_input(files[precision], cfg, cores), 2, batch)
    for precision in PRECISIONS:
        out[f"records_{precision}"] = rate(records_input(files[precision], cfg, cores), batches, batch)
    return {**out, "cpus": children.placement()["cpus"]}


def av2_input_benchmark(config: str | None, overrides: Sequence[str], cores: Sequence[int], labeller: str,
                        logs: int = 4, sweeps: int = 5, points_per_sweep: int = 100_000, batches: int = 8,
                        progress: Callable[[str], None] = print) -> dict:
    """The Argoverse 2 readings (module docstring) on `logs` synthetic logs of `sweeps` sweeps of `points_per_sweep`
    points, on each core count of `cores`, with the labeller module `labeller` (see `av2_child`); `progress` gets
    the summary as JSON."""
    check_core_counts(cores)
    cfg = load_config(config, overrides)
    result = {**header(config, overrides, cfg), "load_average_start": bench.load_average()}
    with tempfile.TemporaryDirectory() as tmp:
        log_dirs = synthetic_av2.write_synthetic_split(tmp, logs, "train", sweeps, seed=17,
                                                       points_per_sweep=points_per_sweep, progress=lambda *a: None)
        first_sweep = argoverse2.read_sweep(log_dirs[0], argoverse2.sweep_timestamps(log_dirs[0])[0])
        result.update({"logs": len(log_dirs), "sweeps_per_log": sweeps, "pairs": len(log_dirs) * (sweeps - 1),
                       "points_per_sweep": len(first_sweep["points_xyz"])})
        job = {"config": child_config(config), "overrides": list(overrides), "logs": log_dirs, "sweeps": sweeps,
               "pairs_timed": 2 * result["pairs"], "out_dir": tmp, "batches": batches, "labeller": labeller}
        result["runs"] = per_core(f"{MODULE}:av2_child", job, cores, "Argoverse 2 input")
    result["per_core_per_s"] = per_core_per_s(result["runs"])
    result["bytes_per_pair"] = {p: result["runs"][str(cores[0])][f"write_{p}"]["bytes_per_pair"] for p in PRECISIONS}
    result["records_over_labels_in_pipeline"] = {
        c: {p: r[f"records_{p}"] / r["labels_in_pipeline"] for p in PRECISIONS}
        for c, r in result["per_core_per_s"].items()}
    result["load_average_end"] = bench.load_average()
    progress(json.dumps({k: result[k] for k in ("points_per_sweep", "per_core_per_s", "bytes_per_pair",
                                                "records_over_labels_in_pipeline")}, indent=1))
    return result


def official_reader_comparison(data_dir: str, frames: int) -> dict:
    """Frames/s of the graph reader (eager and tf.data) vs the official Python frame_utils path, on the first `frames`
    frames of the first segment of `data_dir` (needs the waymo_open_dataset package)."""
    from waymo_open_dataset import dataset_pb2
    from waymo_open_dataset.utils import frame_utils
    records = [r for _, r in waymo.iterate_records(pairs.list_segment_files(data_dir)[0])][:frames]
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

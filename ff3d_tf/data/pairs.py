"""Frame pairs (t-1, t0), or sequences of `data.num_frames` sweeps, -> model input examples, in a `tf.data` pipeline
with no Python per frame.

Per segment file: records are decoded in graph (parallel), consecutive frames are paired (each at most
`max_frame_gap_s` after the one before it, or the file fails naming the record; `skip_bad_records`: the examples
across the gap are skipped), the t-1 cloud is moved into the vehicle frame at t0 with
T = inv(pose_t0) @ pose_tm1 (paper appendix), and the study options (class ablation, density, ground removal) apply.
With `data.num_frames` = N > 2, each example is the current frame and the N - 1 frames before it in the file, each
consecutive two within `max_frame_gap_s`, every past cloud moved into the vehicle frame at t0 by its own pose; a frame
with a t-1 but fewer older frames takes the file's first frame for those it lacks (`schema.FULL_HISTORY_KEY` False:
evaluation reads it, training does not).
Batches are padded to point-count buckets (see `bucket_size`) so that XLA compiles once per bucket.
"""
from __future__ import annotations

import contextlib
import os

import numpy as np
import tensorflow as tf

from ff3d_tf import geometry, schema
from ff3d_tf.config import ABLATED_CLASSES, ConfigError, ExperimentConfig, partner_matters, replace_config
from ff3d_tf.data import pair_records
from ff3d_tf.data.wod import waymo
from ff3d_tf.data.wod.wod_decode import DecodeOptions
from ff3d_tf.data.wod_errors import SOURCE_SEPARATOR, check, parse_tagged_error

_RECORD_INDEX = "record_index"  # a frame's index in its file, beside the decoded frame in the windows
# Bucket sizes are base * {1, 1.5, 2, 3, 4, 6, 8, 12, ...}: at most 50% padding, ~2 buckets per doubling.
_BUCKET_MULTIPLIERS = np.array(sorted({m * 2 ** k for k in range(0, 14) for m in (1.0, 1.5)}))


def bucket_size(num_points: int, base: int) -> int:
    """Smallest bucket >= num_points (Python twin of the in-graph rounding)."""
    sizes = (_BUCKET_MULTIPLIERS * base).astype(np.int64)
    return int(sizes[np.searchsorted(sizes, max(int(num_points), 1))])


def bucket_size_tf(n, base: int):
    sizes = tf.constant((_BUCKET_MULTIPLIERS * base).astype(np.int32))
    return tf.gather(sizes, tf.searchsorted(sizes, tf.reshape(tf.maximum(n, 1), [1]))[0])


def list_segment_files(data_dir_or_glob: str) -> list[str]:
    """TFRecord files of a directory (sorted) or a glob, local or on any `tf.io.gfile` filesystem (gs://, ...).

    Unfinished outputs of the writers (`*.partial`) are never listed.
    """
    gfile = tf.io.gfile
    pattern = os.path.join(data_dir_or_glob, "*.tfrecord*") if gfile.isdir(data_dir_or_glob) else data_dir_or_glob
    files = sorted(f for f in gfile.glob(pattern) if not f.endswith(".partial"))
    if not files:
        raise FileNotFoundError(f"no TFRecord files at {data_dir_or_glob} (expected *.tfrecord)")
    return files


def decode_options(cfg: ExperimentConfig, inference_only: bool = False) -> DecodeOptions:
    return DecodeOptions(tuple(cfg.data.laser_names), tuple(cfg.data.returns), not inference_only)


def make_pair(frame_tm1: dict, frame_t0: dict, cfg: ExperimentConfig, seed=None) -> dict:
    """One model input example (keys: `ff3d_tf.schema.PAIR_KEYS`) from two decoded frames (tensors)."""
    return make_example([frame_t0, frame_tm1], cfg, seed)


def make_example(frames: list, cfg: ExperimentConfig, seed=None) -> dict:
    """One model input example from decoded frames (tensors), newest first: t0, t-1 (the pair's keys,
    `ff3d_tf.schema.PAIR_KEYS`), then any older sweeps (`schema.past_sweep_keys`), each past cloud moved into the
    vehicle frame at t0 by T = inv(pose_t0) @ pose_tk (not moved without `data.ego_motion_compensation`)."""
    frame_t0 = frames[0]
    ex = {"points_xyz_t0": frame_t0["points_xyz"],
          "point_features_t0": tf.stack([frame_t0["intensity"], frame_t0["elongation"]], -1),
          "flow_mps_t0": frame_t0["flow_mps"], "class_id_t0": frame_t0["class_id"]}
    clouds = schema.sweep_clouds(len(frames))
    for cloud, frame in zip(clouds[1:], frames[1:]):
        keys = schema.cloud_keys(cloud)
        if cfg.data.ego_motion_compensation:
            ex[keys["xyz"]] = geometry.transform_points(frame["points_xyz"],
                                                        geometry.t0_from_tm1(frame_t0["pose"], frame["pose"]))
        else:
            ex[keys["xyz"]] = tf.identity(frame["points_xyz"])
        ex[keys["features"]] = tf.stack([frame["intensity"], frame["elongation"]], -1)
    ex = _apply_studies(ex, cfg, seed)
    for cloud, frame in zip(clouds, frames):
        keys = schema.cloud_keys(cloud)
        ex[keys["pose"]] = frame["pose"]
        ex[keys["count"]] = tf.shape(ex[keys["xyz"]])[0]
    return ex


def _cloud_of(key: str) -> str:
    """The cloud ("t0", "tm1", ...) whose points a per-point key follows."""
    return schema.POINT_KEYS[key].cloud


def _keep(ex: dict, keep: dict) -> dict:
    """`ex` with each per-point key's points where `keep[its cloud]` is True."""
    return {k: tf.boolean_mask(v, keep[_cloud_of(k)]) for k, v in ex.items()}


def raw_pair_config(cfg: ExperimentConfig) -> ExperimentConfig:
    """`cfg` with every study off (class ablation, point density, ground removal, no ego-motion compensation), no
    crop, and a WOD source with human labels: `make_pair` keeps every point of both clouds. Pair records store pairs
    so (their reader applies `cfg`'s studies), and predictions on a user's own clouds pair them so (one output row
    per point of the t0 file)."""
    import dataclasses
    data = dataclasses.replace(cfg.data, source="wod", labels="human", crop_to_grid=False, class_ablation="none",
                               point_keep_fraction=1.0, remove_ground_below_z_m=None, ego_motion_compensation=True)
    return dataclasses.replace(cfg, data=data)


def _apply_studies(ex: dict, cfg: ExperimentConfig, seed) -> dict:
    d, g = cfg.data, cfg.grid
    cls = ex["class_id_t0"]
    if d.class_ablation != "none":
        classes, mode = d.class_ablation.rsplit("_", 1)
        ablated = tf.reduce_any(cls[:, None] == tf.constant(ABLATED_CLASSES[classes], tf.int32), axis=1)
        if mode == "stationary":  # paper Table 4 "Stationary": background, no motion
            ex["class_id_t0"] = tf.where(ablated, schema.CLASS_BACKGROUND, cls)
            ex["flow_mps_t0"] = tf.where(ablated[:, None], 0.0, ex["flow_mps_t0"])
        else:  # "Ignored": no target label
            ex["class_id_t0"] = tf.where(ablated, schema.CLASS_NO_LABEL, cls)
    # Every cloud of the example (t0, t-1, older sweeps), with its own seed offset for the density study.
    clouds = [c for c in schema.sweep_clouds(schema.MAX_NUM_FRAMES) if schema.cloud_keys(c)["xyz"] in ex]
    keep = {}
    for offset, cloud in enumerate(clouds):
        p = ex[schema.cloud_keys(cloud)["xyz"]]
        keep[cloud] = tf.ones(tf.shape(p)[:1], tf.bool)
        if d.crop_to_grid:
            keep[cloud] &= ((p[:, 0] >= g.x_range_m[0]) & (p[:, 0] < g.x_range_m[1]) & (p[:, 1] >= g.y_range_m[0]) &
                            (p[:, 1] < g.y_range_m[1]) & (p[:, 2] >= g.z_range_m[0]) & (p[:, 2] <= g.z_range_m[1]))
        if d.remove_ground_below_z_m is not None:
            keep[cloud] &= p[:, 2] >= d.remove_ground_below_z_m
        if d.point_keep_fraction < 1.0:
            keep[cloud] &= tf.random.stateless_uniform(tf.shape(keep[cloud]), seed + offset) < d.point_keep_fraction
    return _keep(ex, keep)


@contextlib.contextmanager
def input_errors_named(files: list[str], options: DecodeOptions | None = None):
    """Turns a decoding error of the input pipeline over `files` into a FrameDecodeError naming file, record and
    field (`waymo.pipeline_error`; `options` as the pipeline decodes, see `decode_options`; pair records by
    `pair_records.locate_fault`); any other error passes unchanged."""
    try:
        yield
    except tf.errors.OpError as err:
        files = list(files)
        if files and all(f.endswith(pair_records.FILE_SUFFIX) for f in files) and \
                parse_tagged_error(err.message) is None:
            bad = pair_records.locate_fault(files) if isinstance(
                err, (tf.errors.DataLossError, tf.errors.InvalidArgumentError)) else None
        else:
            bad = waymo.pipeline_error(err, files, options)
        if bad is None:
            raise
        raise bad from None


def _frames_dataset(path: str, cfg: ExperimentConfig, inference_only: bool, skip_bad_records: bool):
    def with_index(index, frame):  # the record index names a frame out of time order
        return {**frame, _RECORD_INDEX: index}

    return waymo.frames_dataset(path, decode_options(cfg, inference_only), skip_bad_records).map(with_index)


def consecutive_frames(frames: tf.data.Dataset, num_frames: int = 2) -> tf.data.Dataset:
    """(window, real) for each frame after the first: the window is `num_frames` frames as a tuple, newest first
    ((frame t0, frame t-1) for the pair), and `real` how many of its past frames are their own (the others, missing
    at the start of the file, are the file's first frame: `schema.FULL_HISTORY_KEY`). By a scan that carries the
    previous `num_frames - 1` frames, all of them the first frame until there are more.

    Not `Dataset.window`: a window ends silently when its input fails on its first element, so a file truncated
    inside its first records gave no pairs and no error (found by `ff3d_tf.fuzz`).
    """
    none = {k: tf.zeros([d or 0 for d in spec.shape.as_list()], spec.dtype) for k, spec in frames.element_spec.items()}

    def step(state, frame_t0):
        previous, count = state  # the frames before this one, newest first; how many frames came before it
        window = (frame_t0,) + previous
        carried = window[:-1]  # the pair carries the frame alone; longer windows start as the first frame repeated
        if num_frames > 2:
            carried = tf.nest.map_structure(lambda first, later: tf.cond(count > 0, lambda: later, lambda: first),
                                            (frame_t0,) * (num_frames - 1), carried)
        return (carried, count + 1), (window, tf.minimum(count, num_frames - 1))

    windows = frames.scan(((none,) * (num_frames - 1), tf.constant(0, tf.int64)), step)
    return windows.filter(lambda window, real: real > 0)


def _pairs_of_file(path, cfg: ExperimentConfig, inference_only: bool, skip_bad_records: bool, metadata: bool = False):
    frames = _frames_dataset(path, cfg, inference_only, skip_bad_records)
    max_gap_us = int(round(cfg.data.max_frame_gap_s * 1e6))

    def to_example(window, real):  # newest first
        seed = tf.stack([tf.cast(window[0]["timestamp_micros"] % 2147483647, tf.int32), 7])
        ex = make_example(list(window), cfg, seed)
        if len(window) > 2:
            ex[schema.FULL_HISTORY_KEY] = real == len(window) - 1
        if metadata:
            ex[pair_records.TIMESTAMP_KEY] = window[0]["timestamp_micros"] * 1000
            ex[pair_records.PARTNER_TIMESTAMP_KEY] = window[1]["timestamp_micros"] * 1000
            ex[pair_records.SEQUENCE_KEY] = tf.strings.split(path, "/")[-1]
        return ex

    def in_time(newer, older):
        gap_us = newer["timestamp_micros"] - older["timestamp_micros"]
        return (gap_us > 0) & (gap_us <= max_gap_us)

    def close_in_time(window, real):  # every two consecutive real sweeps in order and within the gap
        held = tf.stack([in_time(newer, older) for newer, older in zip(window[:-1], window[1:])])
        return tf.reduce_all(held | (tf.range(len(window) - 1, dtype=real.dtype) >= real))

    def checked_in_time(window, real):
        # Every two consecutive frames of the file are (t0, t-1) of one window, the first that holds them: checking
        # that pair alone names the first frame out of order or after a missing one.
        frame_t0, frame_tm1 = window[0], window[1]
        reason = tf.strings.format(
            "the frame at timestamp_micros {} comes {} us after the one before it (record {}); frames are in time "
            "order and at most data.max_frame_gap_s apart, so a frame is missing or out of order",
            (frame_t0["timestamp_micros"], frame_t0["timestamp_micros"] - frame_tm1["timestamp_micros"],
             frame_tm1[_RECORD_INDEX]))
        source = tf.strings.join([path, SOURCE_SEPARATOR, tf.strings.as_string(frame_t0[_RECORD_INDEX])])
        with tf.control_dependencies([check(in_time(frame_t0, frame_tm1), "timestamp_micros", reason, source)]):
            return tf.nest.map_structure(tf.identity, (window, real))

    def adjacent_records(window, real):
        # A record between them failed to decode and raised its own error; an input pipeline that reads on after an
        # error (prefetching, parallel calls) must not see a second one for the gap that record leaves.
        return tf.equal(window[0][_RECORD_INDEX], window[1][_RECORD_INDEX] + 1)

    windows = consecutive_frames(frames, cfg.data.num_frames)
    # With skip_bad_records an example across a missing or reordered frame is dropped; without it the file fails.
    windows = windows.filter(close_in_time) if skip_bad_records else \
        windows.filter(adjacent_records).map(checked_in_time)
    return windows.map(to_example, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)


def _pairs_of_records(path, cfg: ExperimentConfig, manifest, extras: tuple, metadata: bool, skip: bool,
                      training_labels: bool):
    pseudo = training_labels and cfg.data.labels == "pseudo"
    # Training on pseudo-labels reads them and, where the records have it, which points have one (the loss skips
    # the others).
    if pseudo:
        extras_read = {schema.PSEUDO_FLOW_KEY} | ({schema.PSEUDO_VALID_KEY} & set(manifest.extras))
    wanted = set(extras) | (extras_read if pseudo else set())
    read = tuple(k for k in schema.PAIR_EXTRA_POINT_KEYS if k in wanted)

    point_keys, count_keys, pose_keys = pair_records.record_keys(manifest.num_frames)

    def to_example(record):
        points = {k: record[k] for k in point_keys + read}
        if pseudo:
            points["flow_mps_t0"] = points[schema.PSEUDO_FLOW_KEY]
            if schema.PSEUDO_FLOW_KEY not in extras:
                del points[schema.PSEUDO_FLOW_KEY]
        micros = record[pair_records.TIMESTAMP_KEY] // 1000  # the seed of the decoding path (`_pairs_of_file`)
        ex = _apply_studies(points, cfg, tf.stack([tf.cast(micros % 2147483647, tf.int32), 7]))
        ex.update({k: record[k] for k in pose_keys})
        if schema.FULL_HISTORY_KEY in record:
            ex[schema.FULL_HISTORY_KEY] = record[schema.FULL_HISTORY_KEY]
        ex.update({k: tf.shape(ex[schema.cloud_keys(k[len("num_points_"):])["xyz"]])[0] for k in count_keys})
        if metadata:
            ex.update({k: record[k] for k in pair_records.METADATA_KEYS})
        return ex

    return pair_records.records_dataset(path, manifest, read, skip).map(
        to_example, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)


def check_records_match(manifest, cfg: ExperimentConfig, where: str, inference_only: bool = False,
                        training_labels: bool = False) -> None:
    """ConfigError unless pair records written as `manifest` can serve `cfg` (same lidars and returns, labels;
    `inference_only`: a predictor's input, for which unlabelled records serve; `training_labels`: the training input,
    which reads the labels `data.labels` names, human or not; any other read scores human labels)."""
    d = cfg.data
    if manifest.num_frames != d.num_frames:
        raise ConfigError(f"{where}: the pair records hold {manifest.num_frames} sweeps per example; the config asks "
                          f"for data.num_frames={d.num_frames}: write records with that number, or change the config")
    if d.partner is not None and manifest.partner != d.partner and partner_matters(cfg):
        raise ConfigError(f"{where}: these pair records pair each sweep with the {manifest.partner} one (their "
                          f"manifest's partner); the config asks for data.partner={d.partner}: a model learns the "
                          "order of the sweeps it was trained on. Use records of that order, or leave data.partner "
                          "unset to take the records'")
    if manifest.source == "wod" and (tuple(sorted(manifest.laser_names)), tuple(sorted(manifest.returns))) != \
            (tuple(sorted(d.laser_names)), tuple(sorted(d.returns))):
        raise ConfigError(f"{where}: the pair records hold lasers {manifest.laser_names}, returns "
                          f"{manifest.returns}; the config asks for data.laser_names={d.laser_names}, "
                          f"data.returns={d.returns}: write records with that selection, or change the config")
    if not manifest.human_labels and not inference_only and (d.labels == "human" or not training_labels):
        raise ConfigError(f"{where}: these pair records hold no human flow labels (raw LiDAR): train on their "
                          "pseudo-labels (tools/pseudo_label.py, data.labels=pseudo) or without labels "
                          "(tools/prepare_self_supervision.py, data.labels=self); evaluation needs labelled data")
    if d.labels == "pseudo" and schema.PSEUDO_FLOW_KEY not in manifest.extras:
        raise ConfigError(f"{where}: data.labels=pseudo, but these records hold no pseudo-labels "
                          "(write them with tools/pseudo_label.py)")
    missing_ground = [k for k in schema.ground_keys(manifest.num_frames) if k not in manifest.extras]
    if d.drop_ground and missing_ground:
        raise ConfigError(f"{where}: data.drop_ground=true reads every sweep's ground mask, and these pair records "
                          f"lack {missing_ground}: add them with tools/add_ground_masks.py (Argoverse 2 records "
                          "written with several sweeps carry them all)")


def with_data_partner(cfg: ExperimentConfig, files: list[str]) -> ExperimentConfig:
    """`cfg` with `data.partner` resolved from the data it reads (`schema.PARTNERS`): the pair records' manifest, or
    "previous" for WOD frames read on the fly. A value the config sets must match the records
    (`check_records_match`)."""
    if cfg.data.source != "pair_records":
        partner = "previous"
        if cfg.data.partner not in (None, partner) and partner_matters(cfg):
            raise ConfigError(f"data.partner={cfg.data.partner} with data.source={cfg.data.source}: these frames "
                              "pair each sweep with the previous one; next-sweep partners come with Argoverse 2 pair "
                              "records")
    else:
        manifest = pair_records.manifest_of_files(list(files))
        check_records_match(manifest, cfg, os.path.dirname(files[0]), inference_only=True)
        partner = manifest.partner
    return cfg if cfg.data.partner == partner else replace_config(cfg, {"data.partner": partner})


def pair_dataset(files: list[str], cfg: ExperimentConfig, *, inference_only: bool = False,
                 skip_bad_records: bool | None = None, extras: tuple[str, ...] = (), metadata: bool = False,
                 training_labels: bool = False) -> tf.data.Dataset:
    """Unbatched model input examples of all consecutive frame pairs of the given files, in file order.

    `cfg.data.source` says what the files are: WOD segments (decoded here) or pair records. Pair records may also
    give `extras` (`schema.PAIR_T0_EXTRA_POINT_KEYS`); `metadata` adds `pair_records.METADATA_KEYS` (either source).
    `training_labels`: the flow is the one `cfg.data.labels` trains on (pseudo-labels replace `flow_mps_t0`);
    otherwise always the human labels, which evaluation scores against.
    """
    skip = cfg.data.skip_bad_records if skip_bad_records is None else skip_bad_records
    files_ds = tf.data.Dataset.from_tensor_slices(list(files))
    if cfg.data.source == "pair_records":
        manifest = pair_records.manifest_of_files(list(files))
        check_records_match(manifest, cfg, os.path.dirname(files[0]), inference_only, training_labels)
        if cfg.data.drop_ground:  # the masks `batch_examples` leaves out of the model's input
            extras = tuple(extras) + tuple(k for k in schema.ground_keys(cfg.data.num_frames) if k not in extras)
        fn = lambda f: _pairs_of_records(f, cfg, manifest, tuple(extras), metadata, skip, training_labels)  # noqa
    else:
        if extras:
            raise ValueError(f"extras {extras} come with pair records (data.source=pair_records)")
        fn = lambda f: _pairs_of_file(f, cfg, inference_only, skip, metadata)  # noqa: E731
    return files_ds.interleave(fn, cycle_length=2, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)


def padded_singletons(ds: tf.data.Dataset, bucket_base: int, drop_ground: bool = False):
    """(batch of one example padded to its bucket, the same example unpadded) for each example of `ds`: inference
    input without a tf.data pipeline per example (`drop_ground` as `batch_examples`)."""
    for batch in batch_examples(ds, 1, bucket_base, drop_ground=drop_ground).prefetch(2):
        length = {k: int(batch[schema.cloud_keys(_cloud_of(k))["count"]][0]) for k in batch if k in schema.POINT_KEYS}
        yield batch, {k: v[0, :length[k]] if k in length else v[0]
                      for k, v in batch.items() if not k.startswith("point_mask_")}


def batch_examples(ds: tf.data.Dataset, batch_size: int, bucket_base: int, drop_remainder: bool = False,
                   drop_ground: bool = False):
    """Pads point arrays to a common bucketed size (per cloud) and adds each cloud's mask (`point_mask_t0`,
    `point_mask_tm1`, ...): its real points, with `drop_ground` (`data.drop_ground`) those its ground mask
    (`schema.GROUND_KEY_FORMAT`) does not flag, so that the model reads no ground point of any sweep and predicts 0
    flow at t0's (its output's validity)."""
    ds = ds.padded_batch(batch_size, drop_remainder=drop_remainder)
    clouds = [c for c in schema.sweep_clouds(schema.MAX_NUM_FRAMES) if schema.cloud_keys(c)["xyz"] in ds.element_spec]
    missing = [k for k in (schema.GROUND_KEY_FORMAT.format(cloud=c) for c in clouds) if k not in ds.element_spec]
    if drop_ground and missing:
        raise ConfigError(f"data.drop_ground=true: these examples carry no {', '.join(missing)} (every sweep's ground "
                          "mask): read pair records that hold them (tools/add_ground_masks.py)")

    def pad(batch):
        out = dict(batch)
        for suffix in clouds:
            keys = [k for k in batch if k in schema.POINT_KEYS and _cloud_of(k) == suffix]
            n = tf.shape(batch[schema.cloud_keys(suffix)["xyz"]])[1]
            target = bucket_size_tf(n, bucket_base)
            for k in keys:
                v = batch[k]
                paddings = [[0, 0], [0, target - n]] + [[0, 0]] * (len(v.shape) - 2)
                out[k] = tf.pad(v, paddings, constant_values=tf.cast(schema.POINT_KEYS[k].padding, v.dtype))
            real = tf.sequence_mask(batch[f"num_points_{suffix}"], target)
            # padded_batch fills with 0 (a class id's background); `real` says what is real
            for k in (k for k in keys if k in out and schema.POINT_KEYS[k].padding != 0):
                out[k] = tf.where(real, out[k], tf.cast(schema.POINT_KEYS[k].padding, out[k].dtype))
            if drop_ground:
                real &= ~tf.cast(out[schema.GROUND_KEY_FORMAT.format(cloud=suffix)], tf.bool)
            out[f"point_mask_{suffix}"] = real
        return out

    return ds.map(pad, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)

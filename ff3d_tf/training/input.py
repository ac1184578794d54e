"""The training input: which files a run trains on and the stream of batches the Trainer reads from them.

`training_files` applies `data.max_training_segments` (the data-size study's cap: the first N files); `training_dataset`
is the repeated, shuffled, augmented (`data.augment_*`), batched and bucketed stream, read here or by the workers of
a tf.data service (`ff3d_tf.training.data_service`), with the record extras the loss reads (`loss_extras`). Every
reader of the training input (the Trainer, the lab's lab/tools/benchmark_input.py and lab/tools/benchmark_training.py)
goes through them, so each trains on the same files in the same order.
"""
from __future__ import annotations

import os

import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.config import LOSS_SPECS, ConfigError, ExperimentConfig, loss_labels_problem
from ff3d_tf.data import augment, pair_records, pairs

DATA_SERVICE_JOB = "ff3d_train"  # trainers sharing a tf.data service job read disjoint batches of one stream


def training_files(files: list[str], cfg: ExperimentConfig) -> list[str]:
    """The files a run trains on: the first `data.max_training_segments` of `files` (all of them when it is 0)."""
    cap = cfg.data.max_training_segments
    return list(files[:cap] if cap else files)


def loss_extras(files: list[str], cfg: ExperimentConfig) -> tuple[str, ...]:
    """The extras of `files` (pair records) that the configured loss reads (`config.LOSS_SPECS`): every field it
    needs, and those it may use that the records' manifest lists. ConfigError before any work when the loss cannot
    train on `data.labels`, or the records lack a field the loss needs (naming it and the tool that writes it). None
    for WOD segments."""
    problem = loss_labels_problem(cfg.train.loss, cfg.data.labels)
    if problem:  # the config allows it for evaluating such a model; training cannot
        raise ConfigError(problem)
    spec = LOSS_SPECS[cfg.train.loss]
    needs, may_use = (spec.fields(which, cfg.data.num_frames) for which in ("needs", "may_use"))
    if cfg.data.source != "pair_records" or not files:
        return ()
    held = pair_records.manifest_of_files(list(files)).extras
    missing = [k for k in needs if k not in held]
    if missing:
        raise ConfigError(f"{os.path.dirname(files[0])}: train.loss={cfg.train.loss} needs {missing}, which these "
                          f"pair records do not hold (they hold {list(held) or 'no extras'}): write them with "
                          f"{spec.writer or 'the tool that makes them'}")
    return needs + tuple(k for k in may_use if k in held)


def loss_notice(files: list[str], cfg: ExperimentConfig) -> str | None:
    """The line a trainer prints once at start when the loss runs reduced on `files`: deltaflow without instance
    ids (WOD segments, or records written without them) trains without its instance term. None otherwise. Raises as
    `loss_extras` does (the Trainer calls it first: a loss that cannot train on these files stops before any work)."""
    extras = loss_extras(files, cfg)
    if cfg.train.loss != "deltaflow" or "instance_id_t0" in extras:
        return None
    return ("train.loss=deltaflow: the training data carries no instance ids (instance_id_t0; pair records written "
            "from boxes carry them): training without DeltaFlow's instance term")


def dense_instance_ids(instance_id):
    """[N] int32: each pair's instance ids renumbered 0, 1, ... in order of first appearance (-1 stays -1), so that
    every id is below the pair's point count (what the loss's instance term requires)."""
    unique_ids, index = tf.unique(instance_id)
    renumbered = tf.cumsum(tf.cast(unique_ids >= 0, tf.int32)) - 1
    return tf.where(instance_id >= 0, tf.gather(renumbered, index), -1)


def _training_transforms(ds: tf.data.Dataset, cfg: ExperimentConfig, shard) -> tf.data.Dataset:
    """Per-example transforms of the repeated stream: dense instance ids, then the augmentation, drawn from the seed
    (`train.seed`, the example's position in this pipeline's stream: a resume replays it, `shard` keeps the pipelines
    of one job apart)."""
    if "instance_id_t0" in ds.element_spec:
        ds = ds.map(lambda ex: {**ex, "instance_id_t0": dense_instance_ids(ex["instance_id_t0"])},
                    num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)
    if not augment.is_enabled(cfg.data):
        return ds
    num_shards, shard_index = shard if shard is not None else (1, 0)

    def augmented(position, ex):
        seed = tf.stack([tf.constant(cfg.train.seed, tf.int64), position * num_shards + shard_index])
        return augment.augment_example(ex, cfg.data, seed)

    return ds.enumerate().map(augmented, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)


def training_dataset(files: list[str], cfg: ExperimentConfig, batch_size: int, shard=None, skip_batches: int = 0,
                     data_service_address: str | None = None):
    """Repeated, shuffled, augmented, batched and bucketed training examples of `training_files(files, cfg)`.

    Without a data service the order is seeded (the same on every run), so a resume fast-forwards `skip_batches`
    to the exact position. With `data_service_address` (grpc://host:port of a tf.data service dispatcher), decoding,
    pairing and batching run on the service's workers, the segment files are split among them (dynamic sharding:
    every pair once per epoch) and batches arrive in the order workers finish them: training resumes from its
    checkpoint at the same step with the same weights, but the data order is not replayed.
    """
    # data.labels: the human labels or pseudo-labels; the extras the loss reads
    files = training_files(files, cfg)
    ds = pairs.pair_dataset(files, cfg, training_labels=True, extras=loss_extras(files, cfg))
    if schema.FULL_HISTORY_KEY in ds.element_spec:  # more than 2 sweeps: only examples with all their own history
        ds = ds.filter(lambda ex: ex[schema.FULL_HISTORY_KEY])
    if shard is not None and not data_service_address:
        ds = ds.shard(*shard)
    if cfg.data.cache_decoded:
        ds = ds.cache()
    ds = ds.shuffle(cfg.data.shuffle_buffer, seed=cfg.train.seed, reshuffle_each_iteration=True).repeat()
    ds = _training_transforms(ds, cfg, None if data_service_address else shard)
    ds = pairs.batch_examples(ds, batch_size, cfg.data.point_bucket_base, drop_remainder=True,
                              drop_ground=cfg.data.drop_ground)
    if data_service_address:
        ds = ds.apply(tf.data.experimental.service.distribute(
            processing_mode=tf.data.experimental.service.ShardingPolicy.DYNAMIC, service=data_service_address,
            job_name=DATA_SERVICE_JOB))
    elif skip_batches:
        ds = ds.skip(skip_batches)
    return ds.prefetch(2)

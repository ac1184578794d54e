"""The training input: which files a run trains on and the stream of batches the Trainer reads from them.

`training_files` applies `data.max_training_segments` (the data-size study's cap: the first N files); `training_dataset`
is the repeated, shuffled, batched and bucketed stream, read here or by the workers of a tf.data service
(`ff3d_tf.training.data_service`). Every reader of the training input (the Trainer, tools/benchmark_input.py,
tools/benchmark_training.py) goes through them, so each trains on the same files in the same order.
"""
from __future__ import annotations

import tensorflow as tf

from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import pairs

DATA_SERVICE_JOB = "ff3d_train"  # trainers sharing a tf.data service job read disjoint batches of one stream


def training_files(files: list[str], cfg: ExperimentConfig) -> list[str]:
    """The files a run trains on: the first `data.max_training_segments` of `files` (all of them when it is 0)."""
    cap = cfg.data.max_training_segments
    return list(files[:cap] if cap else files)


def training_dataset(files: list[str], cfg: ExperimentConfig, batch_size: int, shard=None, skip_batches: int = 0,
                     data_service_address: str | None = None):
    """Repeated, shuffled, batched and bucketed training examples of `training_files(files, cfg)`.

    Without a data service the order is seeded (the same on every run), so a resume fast-forwards `skip_batches`
    to the exact position. With `data_service_address` (grpc://host:port of a tf.data service dispatcher), decoding,
    pairing and batching run on the service's workers, the segment files are split among them (dynamic sharding:
    every pair once per epoch) and batches arrive in the order workers finish them: training resumes from its
    checkpoint at the same step with the same weights, but the data order is not replayed.
    """
    # data.labels: the human labels or pseudo-labels
    ds = pairs.pair_dataset(training_files(files, cfg), cfg, training_labels=True)
    if shard is not None and not data_service_address:
        ds = ds.shard(*shard)
    if cfg.data.cache_decoded:
        ds = ds.cache()
    ds = ds.shuffle(cfg.data.shuffle_buffer, seed=cfg.train.seed, reshuffle_each_iteration=True).repeat()
    ds = pairs.batch_examples(ds, batch_size, cfg.data.point_bucket_base, drop_remainder=True)
    if data_service_address:
        ds = ds.apply(tf.data.experimental.service.distribute(
            processing_mode=tf.data.experimental.service.ShardingPolicy.DYNAMIC, service=data_service_address,
            job_name=DATA_SERVICE_JOB))
    elif skip_batches:
        ds = ds.skip(skip_batches)
    return ds.prefetch(2)

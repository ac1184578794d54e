"""Custom tf.distribute training loop for FastFlow3D.

MirroredStrategy over the visible GPUs (the CPU when there is none), MultiWorkerMirroredStrategy when TF_CONFIG is set;
`distribute_datasets_from_function`; loss scaled by the global batch; the forward and backward pass XLA-compiled;
checkpoints every `checkpoint_every_steps` and on SIGINT/SIGTERM; resume from `--model_dir` at the same step with the
same optimizer state and the same data order (the deterministic stream is fast-forwarded); non-finite steps are
skipped and counted and never reach the weights.
"""
from __future__ import annotations

import json
import logging
import os
import signal
import time

import keras
import numpy as np
import tensorflow as tf

from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import pairs
from ff3d_tf.training.losses import per_sample_flow_loss
from ff3d_tf.training.metrics import SceneFlowMetrics
from ff3d_tf.inference.predictor import compiled_forward, model_inputs
from ff3d_tf.model import build_model

_LOG = logging.getLogger(__name__)


class NonFiniteLossError(RuntimeError):
    """Too many non-finite steps in a row (`train.max_nonfinite_steps_in_row`); the weights were never touched."""


def make_strategy() -> tf.distribute.Strategy:
    if os.environ.get("TF_CONFIG"):
        return tf.distribute.MultiWorkerMirroredStrategy()
    gpus = tf.config.list_logical_devices("GPU")
    if gpus:
        return tf.distribute.MirroredStrategy([d.name for d in gpus])
    cpus = tf.config.list_logical_devices("CPU")
    return tf.distribute.MirroredStrategy([d.name for d in cpus]) if len(cpus) > 1 else \
        tf.distribute.OneDeviceStrategy("/cpu:0")


def learning_rate_schedule(cfg: ExperimentConfig):
    """Constant (the paper) or linear warm-up then cosine decay over `train.num_steps`."""
    t = cfg.train
    if t.lr_schedule == "constant" and not t.warmup_steps:
        return t.learning_rate
    if t.lr_schedule == "constant":
        return keras.optimizers.schedules.CosineDecay(0.0, 1, alpha=1.0, warmup_target=t.learning_rate,
                                                      warmup_steps=t.warmup_steps)
    return keras.optimizers.schedules.CosineDecay(
        t.learning_rate if not t.warmup_steps else 0.0, max(t.num_steps - t.warmup_steps, 1),
        alpha=t.lr_final_fraction, warmup_target=t.learning_rate if t.warmup_steps else None,
        warmup_steps=t.warmup_steps)


def training_dataset(files: list[str], cfg: ExperimentConfig, batch_size: int, shard=None, skip_batches: int = 0):
    """Repeated, shuffled (seeded: the same order on every run), batched and bucketed training examples."""
    ds = pairs.pair_dataset(files, cfg)
    if shard is not None:
        ds = ds.shard(*shard)
    if cfg.data.cache_decoded:
        ds = ds.cache()
    ds = ds.shuffle(cfg.data.shuffle_buffer, seed=cfg.train.seed, reshuffle_each_iteration=True).repeat()
    ds = pairs.batch_examples(ds, batch_size, cfg.data.point_bucket_base, drop_remainder=True)
    if skip_batches:
        ds = ds.skip(skip_batches)
    return ds.prefetch(2)


class Trainer:
    def __init__(self, cfg: ExperimentConfig, model_dir: str, train_files: list[str], val_files: list[str] = (),
                 strategy: tf.distribute.Strategy | None = None, log_fn=print):
        self.cfg, self.model_dir = cfg, model_dir
        self.train_files, self.val_files = list(train_files), list(val_files)
        self.strategy = strategy or make_strategy()
        self.log = log_fn
        self._stop_signal = None
        keras.utils.set_random_seed(cfg.train.seed)  # same initial weights for the same seed (reproducible runs)
        with self.strategy.scope():
            self.model = build_model(cfg)
            self.optimizer = keras.optimizers.Adam(learning_rate_schedule(cfg), beta_1=cfg.train.beta_1,
                                                   beta_2=cfg.train.beta_2)
            self.optimizer.build(self.model.trainable_variables)
            self.step = tf.Variable(0, dtype=tf.int64, trainable=False, name="step")
            self.nonfinite_total = tf.Variable(0, dtype=tf.int64, trainable=False, name="nonfinite_total")
            self.nonfinite_in_row = tf.Variable(0, dtype=tf.int64, trainable=False, name="nonfinite_in_row")
        self.checkpoint = tf.train.Checkpoint(model=self.model, optimizer=self.optimizer, step=self.step,
                                              nonfinite_total=self.nonfinite_total,
                                              nonfinite_in_row=self.nonfinite_in_row)
        self.manager = tf.train.CheckpointManager(self.checkpoint, os.path.join(model_dir, "checkpoints"),
                                                  max_to_keep=cfg.train.keep_checkpoints)
        self._grad_fn = tf.function(self._loss_and_grads, jit_compile=cfg.model.jit_compile, reduce_retracing=True)

    # -- steps -------------------------------------------------------------------------------------------------
    def _loss_and_grads(self, batch):
        cfg = self.cfg
        with tf.GradientTape() as tape:
            out = self.model(model_inputs(batch), training=True)
            valid = out["point_valid"] & batch["point_mask_t0"]
            per_sample = per_sample_flow_loss(batch["flow_mps_t0"], out["flow_mps"], batch["class_id_t0"], valid,
                                              cfg.train.background_weight)
            loss = tf.nn.compute_average_loss(per_sample, global_batch_size=cfg.train.global_batch_size)
        grads = tape.gradient(loss, self.model.trainable_variables)
        return loss, grads

    def _replica_step(self, batch):
        loss, grads = self._grad_fn(batch)
        ctx = tf.distribute.get_replica_context()
        # Sum over replicas here, so every replica holds the global loss and gradients.
        return ctx.all_reduce(tf.distribute.ReduceOp.SUM, loss), ctx.all_reduce(tf.distribute.ReduceOp.SUM, grads)

    @tf.function
    def _train_step(self, iterator):
        loss, grads = self.strategy.run(self._replica_step, args=(next(iterator),))
        loss = self.strategy.experimental_local_results(loss)[0]
        grads = [self.strategy.experimental_local_results(g)[0] for g in grads]
        grad_norm = tf.linalg.global_norm(grads)
        finite = tf.math.is_finite(loss) & tf.math.is_finite(grad_norm)

        def apply():
            g = grads
            if self.cfg.train.grad_clip_norm is not None:
                g, _ = tf.clip_by_global_norm(g, self.cfg.train.grad_clip_norm, use_norm=grad_norm)
            # Cross-replica context: the optimizer updates every mirrored copy with the same global gradients.
            self.optimizer.apply_gradients(zip(g, self.model.trainable_variables))
            self.nonfinite_in_row.assign(0)
            return tf.constant(True)

        def skip():
            self.nonfinite_total.assign_add(1)
            self.nonfinite_in_row.assign_add(1)
            return tf.constant(False)

        tf.cond(finite, apply, skip)
        self.step.assign_add(1)
        return loss

    # -- loop --------------------------------------------------------------------------------------------------
    def _install_signal_handlers(self):
        def handler(signum, _frame):
            self._stop_signal = signum
        previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        return previous

    def train(self, num_steps: int | None = None) -> dict:
        cfg = self.cfg
        num_steps = cfg.train.num_steps if num_steps is None else num_steps
        tf.io.gfile.makedirs(self.model_dir)  # local or gs:// alike
        cfg.save(os.path.join(self.model_dir, "config.yaml"))
        if self.manager.latest_checkpoint:
            self.checkpoint.restore(self.manager.latest_checkpoint)
            self.log(f"resumed from {self.manager.latest_checkpoint} at step {int(self.step.numpy())}")
        start_step = int(self.step.numpy())
        if start_step >= num_steps:
            self.log(f"already at step {start_step} >= {num_steps}; nothing to do")
            return {"step": start_step}
        global_batch = cfg.train.global_batch_size
        if global_batch % self.strategy.num_replicas_in_sync:
            raise ValueError(f"train.global_batch_size={global_batch} is not divisible by the "
                             f"{self.strategy.num_replicas_in_sync} replicas")

        def dataset_fn(ctx: tf.distribute.InputContext):
            per_replica = ctx.get_per_replica_batch_size(global_batch)
            return training_dataset(self.train_files, cfg, per_replica,
                                    shard=(ctx.num_input_pipelines, ctx.input_pipeline_id)
                                    if ctx.num_input_pipelines > 1 else None,
                                    # each step takes one batch per replica fed by this pipeline
                                    skip_batches=start_step * ctx.num_replicas_in_sync // ctx.num_input_pipelines)

        dist_ds = self.strategy.distribute_datasets_from_function(dataset_fn)
        iterator = iter(dist_ds)
        writer = tf.summary.create_file_writer(os.path.join(self.model_dir, "train"))
        previous = self._install_signal_handlers()
        t_start, last_log_t, last_log_step = time.time(), time.time(), start_step
        loss_value = float("nan")
        history = []
        try:
            while int(self.step.numpy()) < num_steps:
                with pairs.input_errors_named(self.train_files):  # a bad record stops here, before any weight update
                    loss = self._train_step(iterator)
                step = int(self.step.numpy())
                loss_value = float(loss.numpy())
                if int(self.nonfinite_in_row.numpy()) >= cfg.train.max_nonfinite_steps_in_row:
                    self.manager.save(checkpoint_number=step)
                    raise NonFiniteLossError(
                        f"{int(self.nonfinite_in_row.numpy())} non-finite steps in a row at step {step} (skipped, "
                        f"weights untouched; {int(self.nonfinite_total.numpy())} in total). Check the input data "
                        f"and lower train.learning_rate or set train.grad_clip_norm")
                if step % cfg.train.log_every_steps == 0 or step == num_steps:
                    now = time.time()
                    rate = (step - last_log_step) / max(now - last_log_t, 1e-9)
                    eta = (num_steps - step) / max(rate, 1e-9)
                    self.log(f"step {step}/{num_steps} loss {loss_value:.4f} {rate:.2f} steps/s "
                             f"ETA {int(eta // 60)}m{int(eta % 60):02d}s skipped_nonfinite "
                             f"{int(self.nonfinite_total.numpy())}")
                    last_log_t, last_log_step = now, step
                    with writer.as_default(step=step):
                        tf.summary.scalar("loss", loss_value)
                        tf.summary.scalar("learning_rate", float(self.optimizer.learning_rate.numpy()))
                        tf.summary.scalar("steps_per_second", rate)
                        tf.summary.scalar("skipped_nonfinite_steps", int(self.nonfinite_total.numpy()))
                    history.append((step, loss_value))
                if step % cfg.train.checkpoint_every_steps == 0:
                    self.manager.save(checkpoint_number=step)
                if self.val_files and cfg.train.eval_every_steps and step % cfg.train.eval_every_steps == 0:
                    self.evaluate_subset(step)
                if self._stop_signal is not None:
                    path = self.manager.save(checkpoint_number=step)
                    self.log(f"interrupted by signal {self._stop_signal} at step {step}; checkpoint {path}; "
                             f"run the same command again to resume")
                    return {"step": step, "loss": loss_value, "interrupted": True}
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
        step = int(self.step.numpy())
        if self.manager.latest_checkpoint is None or not self.manager.latest_checkpoint.endswith(f"-{step}"):
            self.manager.save(checkpoint_number=step)
        self.log(f"finished {step - start_step} steps in {time.time() - t_start:.1f} s")
        with tf.io.gfile.GFile(os.path.join(self.model_dir, "train_history.json"), "w") as f:
            json.dump({"loss": history}, f)
        return {"step": step, "loss": loss_value, "interrupted": False}

    def evaluate_subset(self, step: int) -> dict:
        """Per-class metrics on the first `eval_num_batches` validation batches, written to TensorBoard."""
        cfg = self.cfg
        metric = SceneFlowMetrics()
        ds = pairs.batch_examples(pairs.pair_dataset(self.val_files, cfg), 1, cfg.data.point_bucket_base)
        predict = compiled_forward(self.model, cfg.model.jit_compile)
        for batch in ds.take(cfg.train.eval_num_batches):
            out = predict(model_inputs(batch))
            metric.update_state(batch["flow_mps_t0"], out["flow_mps"], batch["class_id_t0"],
                                point_valid=out["point_valid"] & batch["point_mask_t0"])
        result = metric.result()
        writer = tf.summary.create_file_writer(os.path.join(self.model_dir, "eval"))
        with writer.as_default(step=step):
            for key in ("all/all/mean_l2_mps", "all/moving/mean_l2_mps", "all/stationary/mean_l2_mps",
                        "vehicle/moving/mean_l2_mps", "pedestrian/moving/mean_l2_mps", "cyclist/moving/mean_l2_mps",
                        "background/all/mean_l2_mps", "three_way/mean_epe_m"):
                if not np.isnan(result[key]):
                    tf.summary.scalar(key, result[key])
        self.log(f"eval@{step}: all/moving {result['all/moving/mean_l2_mps']:.3f} m/s, all/stationary "
                 f"{result['all/stationary/mean_l2_mps']:.3f} m/s")
        return result

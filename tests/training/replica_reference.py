"""The two-replica reference of the training step, written out with one model and no strategy (used by the
distributed and multi-worker tests).

Semantics (the paper's setting, per-replica BatchNorm): each replica runs forward/backward on its own samples with its
own batch statistics; the loss (`train.loss`) is summed over samples and divided by the global batch; gradients are
summed over replicas and applied once; each BatchNorm moving statistic becomes the mean of the replicas' updated
values.
"""
import numpy as np
import tensorflow as tf

from ff3d_tf.config import replace_config
from ff3d_tf.data import pairs
from ff3d_tf.model.forward import model_inputs
from ff3d_tf.model import build_model
from ff3d_tf.model.losses import per_sample_training_loss
from ff3d_tf.model.step import make_optimizer

GLOBAL_BATCH = 2


def replica_config(tiny_config):
    return replace_config(tiny_config, {"train.global_batch_size": GLOBAL_BATCH, "train.log_every_steps": 1,
                                        "train.checkpoint_every_steps": 1000, "train.eval_every_steps": 0,
                                        "train.learning_rate": 1e-2})


def batches(segment, cfg, count):
    """`count` global batches of GLOBAL_BATCH pairs (padded to one bucket), as NumPy dicts."""
    ds = pairs.batch_examples(pairs.pair_dataset([segment], cfg).repeat(), GLOBAL_BATCH,
                              cfg.data.point_bucket_base, drop_remainder=True)
    return [{k: v.numpy() for k, v in b.items()} for b in ds.take(count)]


def moving_stats(model):
    return [v for v in model.non_trainable_variables]


class Reference:
    """One model, no strategy: per-sample forward/backward, summed gradients, one Adam update, mean BN statistics."""

    def __init__(self, cfg, weights):
        self.cfg = cfg
        # model.compile=auto resolved as the Trainer resolves it (job "train"): on a CPU where TensorFlow's oneDNN is
        # off (AVX2: AMD Zen 3) that is xla for training but hybrid for inference, and Adam's first steps amplify
        # the two modes' rounding differences to ~1e-3 in the weights.
        self.model = build_model(cfg, job="train")
        self.jit_compile = self.model.compile_mode == "xla"  # the Trainer's forward + backward as one XLA program
        self.model.set_weights(weights)
        self.optimizer = make_optimizer(cfg)
        self.optimizer.build(self.model.trainable_variables)
        # One function for every step: traced (and in mode xla compiled) once per bucket, as the trainer's.
        self._grad_fn = tf.function(self._sample_loss_and_grads, jit_compile=self.jit_compile, reduce_retracing=True)

    def _sample_loss_and_grads(self, sample):
        with tf.GradientTape() as tape:
            out = self.model(model_inputs(sample), training=True, inline_stages=self.jit_compile)
            loss = tf.reduce_sum(per_sample_training_loss(sample, out, self.cfg.train.background_weight,
                                                          loss=self.cfg.train.loss)) / GLOBAL_BATCH
        return loss, tape.gradient(loss, self.model.trainable_variables)

    def step(self, batch):
        """One global batch: sample i is replica i's."""
        return self.step_samples([{k: v[i:i + 1] for k, v in batch.items()} for i in range(GLOBAL_BATCH)])

    def step_samples(self, samples):
        """`samples[i]`: replica i's per-replica batch of one pair (each padded to its own bucket).

        Compiled as the trainer compiles its per-replica step, so both run the same XLA program per sample (an
        eager reference differs in float rounding, which Adam's first steps amplify where |gradient| ~ epsilon).
        """
        grad_fn = self._grad_fn
        start = [v.numpy() for v in moving_stats(self.model)]
        grads_sum, loss_sum, updated = None, 0.0, []
        for sample in samples:
            for v, s in zip(moving_stats(self.model), start):
                v.assign(s)  # every replica starts from the same moving statistics
            loss, grads = grad_fn(sample)
            grads_sum = grads if grads_sum is None else [a + b for a, b in zip(grads_sum, grads)]
            loss_sum += float(loss)
            updated.append([v.numpy() for v in moving_stats(self.model)])
        for i, v in enumerate(moving_stats(self.model)):
            v.assign(np.mean([u[i] for u in updated], axis=0))
        self.optimizer.apply_gradients(zip(grads_sum, self.model.trainable_variables))
        return loss_sum

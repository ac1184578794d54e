"""One training step, written once for every runner: the Trainer (`ff3d_tf.training.trainer`, under tf.distribute)
and the portable export (`ff3d_tf.training.xla_step_export.train_step_fn`, one XLA program).

A step is a function of tensors: `TrainState` (weights, BatchNorm statistics, Adam's slots and iteration count) and
a labelled batch in, the new `TrainState` with the loss and the gradients' global norm out (`StepResult`):

  loss, gradients, new BN statistics   `loss_and_grads_fn` (`batch_flow_loss`, the model run with `training=True`)
  -> all_reduce (optional)             the runner's cross-replica reduction (identity on one device)
  -> global norm, clipping             `train.grad_clip_norm` (None: no clipping)
  -> Adam                              `adam_update` (`adam_apply`: Keras 3's Adam written out)
  -> non-finite skip                   a non-finite loss or norm changes nothing: weights, BN statistics, slots,
                                       iteration count (the runner counts it)

The runner wraps `loss_and_grads_fn`'s function as it compiles it (the Trainer: one XLA program in compile mode
"xla", the reduction outside XLA) and keeps the state where it lives (the Trainer: in the model's and the Keras
optimizer's variables, so checkpoints keep their layout).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import keras
import tensorflow as tf

from ff3d_tf.config import ExperimentConfig
from ff3d_tf.model.forward import model_inputs
from ff3d_tf.model.losses import LossContext, batch_flow_loss

ADAM_EPSILON = 1e-7  # Keras' default, named here because the step's own Adam uses it too


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


def make_optimizer(cfg: ExperimentConfig) -> keras.optimizers.Optimizer:
    """Adam with the paper's betas and the configured learning-rate schedule: the holder of the Trainer's slots (and
    of their checkpoint layout); `adam_update` computes its update."""
    return keras.optimizers.Adam(learning_rate_schedule(cfg), beta_1=cfg.train.beta_1, beta_2=cfg.train.beta_2,
                                 epsilon=ADAM_EPSILON)


class TrainState(NamedTuple):
    """What one step reads and writes, in this order (also the flat order of `tf.nest.flatten`): `weights` in
    `model.trainable_variables` order, `bn_statistics` in `model.non_trainable_variables` order, Adam's `adam_m` and
    `adam_v` one per weight, and `iterations` (the updates applied so far: Adam's step count, int32 or int64)."""
    weights: list
    bn_statistics: list
    adam_m: list
    adam_v: list
    iterations: tf.Tensor


class StepResult(NamedTuple):
    """A step's results: the new state (the old one where not `finite`), the global batch's loss, the global norm of
    its gradients before clipping, and whether both were finite (the update was applied)."""
    state: TrainState
    loss: tf.Tensor
    grad_norm: tf.Tensor
    finite: tf.Tensor


def loss_and_grads_fn(cfg: ExperimentConfig, model, global_batch_size: int, inline_stages: bool = False,
                      on_variables: bool = False):
    """`(weights, bn_statistics, batch) -> (loss, grads, new_bn_statistics)`: `batch_flow_loss` (`train.loss`) of
    `model` run with `training=True` on `batch` (inputs, labels and the extras the loss reads; the loss divided by
    `global_batch_size`), its gradients with respect to the weights, and the BatchNorm statistics that forward
    updated.

    Stateless (default): the model runs on the given values (`model.stateless_call`) and no variable changes.
    `on_variables`: the model runs on its own variables, which must hold `weights` and `bn_statistics` (the Trainer,
    in every compile mode: "hybrid" updates BatchNorm statistics inside its stages' own XLA functions, which
    `stateless_call` cannot collect); its BatchNorm variables then hold the new statistics too.
    `inline_stages=True` where the caller compiles this whole function with XLA (see `FastFlow3D.call`).
    """
    context = LossContext.of(cfg)  # what `train.loss` reads of the config (config.LOSS_SPECS: labels and fields)

    def loss_and_grads(weights, bn_statistics, batch):
        with tf.GradientTape() as tape:
            if on_variables:
                sources = model.trainable_variables
                outputs = model(model_inputs(batch), training=True, inline_stages=inline_stages)
                new_bn_statistics = [v.value for v in model.non_trainable_variables]
            else:
                sources = weights
                tape.watch(weights)
                outputs, new_bn_statistics = model.stateless_call(weights, bn_statistics, model_inputs(batch),
                                                                  training=True, inline_stages=inline_stages)
            loss = batch_flow_loss(batch, outputs, cfg.train.background_weight, global_batch_size,
                                   loss=cfg.train.loss, context=context)
        return loss, tape.gradient(loss, sources), list(new_bn_statistics)

    return loss_and_grads


def adam_apply(params: list, grads: list, m: list, v: list, step, learning_rate, beta_1: float, beta_2: float,
               epsilon: float) -> tuple[list, list, list]:
    """One Adam update of the tensors `params` (a list; `grads`, `m`, `v` alike, one per tensor): the project's one
    Adam arithmetic, `keras.optimizers.Adam.update_step` (Keras 3) written out, the same operations in the same order:

      t = step + 1, alpha = learning_rate sqrt(1 - b2^t) / (1 - b1^t),
      m += (g - m)(1 - b1), v += (g^2 - v)(1 - b2), w -= m alpha / (sqrt(v) + eps).

    `step`: the updates applied before this one (an integer tensor); `learning_rate` a number or scalar tensor.
    Returns (new params, new m, new v). Pure tensors, no variables: usable inside any compiled loop
    (`ff3d_tf.labels.nsfp` fits its MLPs with it)."""
    dtype = params[0].dtype
    lr = tf.cast(learning_rate, dtype)
    local_step = tf.cast(step + 1, dtype)
    alpha = lr * tf.sqrt(1 - tf.pow(tf.cast(beta_2, dtype), local_step)) / (
        1 - tf.pow(tf.cast(beta_1, dtype), local_step))
    grads = [tf.cast(g, dtype) for g in grads]
    m = [mi + (g - mi) * (1 - beta_1) for mi, g in zip(m, grads)]
    v = [vi + (tf.square(g) - vi) * (1 - beta_2) for vi, g in zip(v, grads)]
    params = [w - mi * alpha / (tf.sqrt(vi) + epsilon) for w, mi, vi in zip(params, m, v)]
    return params, m, v


def adam_update(cfg: ExperimentConfig, state: TrainState, grads: list) -> TrainState:
    """`state` after one Adam update with `grads` (`adam_apply` with the configured learning rate at
    `state.iterations`, betas and `ADAM_EPSILON`), then the iteration count + 1 (BatchNorm statistics unchanged).

    Written out because Keras' stateless form, `optimizer.stateless_apply`, raises on the TensorFlow backend
    (keras/src/backend/tensorflow/optimizer.py: "not supported with the TensorFlow backend (as it is incompatible
    with tf.distribute)"); tests/model/test_step.py checks it against the optimizer itself.
    """
    schedule = learning_rate_schedule(cfg)
    learning_rate = schedule(state.iterations) if callable(schedule) else schedule
    weights, adam_m, adam_v = adam_apply(state.weights, grads, state.adam_m, state.adam_v, state.iterations,
                                         learning_rate, cfg.train.beta_1, cfg.train.beta_2, ADAM_EPSILON)
    return TrainState(weights, state.bn_statistics, adam_m, adam_v, state.iterations + 1)


def train_step_fn(cfg: ExperimentConfig, loss_and_grads: Callable, all_reduce: Callable | None = None):
    """`(state: TrainState, batch) -> StepResult`: one training step (see the module docstring).

    `loss_and_grads`: a `loss_and_grads_fn` function, as the runner compiles it. `all_reduce(loss, grads,
    new_bn_statistics)` returns the three over all replicas (the Trainer: loss and gradients summed, statistics
    averaged); None on one device.
    """
    clip_norm = cfg.train.grad_clip_norm

    def step(state: TrainState, batch: dict) -> StepResult:
        loss, grads, new_bn_statistics = loss_and_grads(state.weights, state.bn_statistics, batch)
        if all_reduce is not None:
            loss, grads, new_bn_statistics = all_reduce(loss, grads, new_bn_statistics)
        grad_norm = tf.linalg.global_norm(grads)
        finite = tf.math.is_finite(loss) & tf.math.is_finite(grad_norm)
        if clip_norm is not None:
            grads, _ = tf.clip_by_global_norm(grads, clip_norm, use_norm=grad_norm)
        updated = adam_update(cfg, state._replace(bn_statistics=new_bn_statistics), grads)
        new_state = tf.nest.map_structure(lambda new, old: tf.where(finite, new, old), updated, state)
        return StepResult(new_state, loss, grad_norm, finite)

    return step

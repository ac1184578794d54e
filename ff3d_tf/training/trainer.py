"""Custom tf.distribute training loop for FastFlow3D.

MirroredStrategy over the visible GPUs (the CPU when there is none), MultiWorkerMirroredStrategy when TF_CONFIG is set
(`cluster.make_strategy`); `distribute_datasets_from_function` over the training input (`input.py`); the step of
`ff3d_tf.model.step` (loss scaled by the global batch, gradients summed over replicas, Adam), its forward and backward
pass XLA-compiled; checkpoints every `checkpoint_every_steps` and on SIGINT/SIGTERM; resume from `--model_dir` at the
same step with the same optimizer state and the same data order (the deterministic stream is fast-forwarded);
non-finite steps are skipped and counted and never reach the weights; every `eval_every_steps` the evaluation of
`evaluation.py` on a few validation pairs.

Faults of a multi-worker job (see README, "Faults and preemption"; the machinery is `cluster.py`):
- a lost worker (killed, stopped, unreachable) ends every other worker within `train.peer_timeout_s` with
  `cluster.PeerLostError` (one line naming the lost task; `tools/train.py` exits with `EXIT_PEER_LOST`), never with
  a checkpoint of the failed step: the collectives' own timeout, TensorFlow's coordination-service heartbeat and a
  step watchdog bound the wait;
- SIGTERM/SIGINT to any one worker stops all of them after the same step: every step all-reduces a "stop" flag
  with its gradients, so every worker sees the request at the same step, saves it and returns `preempted`
  (`EXIT_PREEMPTED`). Restarting the same commands resumes from the chief's newest intact checkpoint.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import signal
import time

import keras
import numpy as np
import tensorflow as tf

from ff3d_tf import cpu, internals
from ff3d_tf.config import ConfigError, ExperimentConfig
from ff3d_tf.data import pairs
from ff3d_tf.checkpoints import restore_newest_intact, with_model_definition
from ff3d_tf.model import build_model
from ff3d_tf.model import plan as plan_lib
from ff3d_tf.model import step as step_lib
from ff3d_tf.model.forward import ModelPredictor
from ff3d_tf.model.step import make_optimizer
from ff3d_tf.training.cluster import (EXIT_PREEMPTED, PeerLostError, Watchdog, cluster_tasks, is_peer_error,
                                      lost_peer_error, lost_task, make_strategy, replica_stop_requests, short_reason,
                                      stop_request_bit, tasks_in_stop_mask)
from ff3d_tf.training.evaluation import evaluate, write_summaries
from ff3d_tf.training.input import loss_notice, training_dataset, training_files

_LOG = logging.getLogger(__name__)


def _history_rule(num_frames: int) -> str:
    """Which examples of several sweeps train (`training.input` filters the others out), said once."""
    return (f"with data.num_frames={num_frames} only examples whose every past slot holds its own sweep train (a "
            f"log's first {num_frames - 2} examples read its first sweep instead and are left out)")


def weights_fingerprint(model) -> str:
    """sha256 of every weight's bytes, in order: equal fingerprints mean bit-identical models (e.g. across workers)."""
    digest = hashlib.sha256()
    for v in model.weights:
        digest.update(np.ascontiguousarray(np.asarray(v)).tobytes())
    return digest.hexdigest()[:16]


class NonFiniteLossError(RuntimeError):
    """Too many non-finite steps in a row (`train.max_nonfinite_steps_in_row`); the weights were never touched."""


def _chief_and_write_dir(strategy: tf.distribute.Strategy, model_dir: str) -> tuple[bool, str]:
    """(is this the chief, where this process writes checkpoints). Single-process training is its own chief."""
    resolver = getattr(strategy, "cluster_resolver", None)
    task_type = getattr(resolver, "task_type", None)
    task_id = getattr(resolver, "task_id", None)
    if task_type is None or task_type == "chief" or (task_type == "worker" and task_id == 0 and
                                                     "chief" not in resolver.cluster_spec().as_dict()):
        return True, model_dir
    return False, os.path.join(model_dir, f"tmp_{task_type}_{task_id}")


def _over_replicas(loss, grads, new_bn_statistics):
    """The step's reduction in replica context: every replica gets the global loss and gradients (summed: each
    replica's loss is already divided by the global batch) and the replicas' mean BatchNorm moving statistics (each
    replica updated them from its own batch; Keras creates them with aggregation "none", so without this the copies
    drift apart and a checkpoint keeps replica 0's)."""
    ctx = tf.distribute.get_replica_context()
    if ctx.num_replicas_in_sync > 1:
        new_bn_statistics = ctx.all_reduce(tf.distribute.ReduceOp.MEAN, new_bn_statistics)
    return (ctx.all_reduce(tf.distribute.ReduceOp.SUM, loss), ctx.all_reduce(tf.distribute.ReduceOp.SUM, grads),
            new_bn_statistics)


class Trainer:
    """The training loop. Multi-worker: every worker runs the same steps; only the chief writes into `model_dir`
    (checkpoints, summaries, config, history). The others save into a temporary directory of their own, removed at
    the end (TF's multi-worker checkpointing pattern), and all of them restore from the chief's checkpoints."""

    def __init__(self, cfg: ExperimentConfig, model_dir: str, train_files: list[str], val_files: list[str] = (),
                 strategy: tf.distribute.Strategy | None = None, log_fn=print, data_service_address: str | None = None,
                 plan: plan_lib.ExecutionPlan | None = None):
        self.train_files, self.val_files = training_files(train_files, cfg), list(val_files)
        # The sweep order the model learns (data.partner), from its data, saved with it; a model_dir that holds a
        # model of another definition stops here, before anything is restored or written.
        if self.train_files:
            cfg = pairs.with_data_partner(cfg, self.train_files)
        cfg = with_model_definition(cfg, model_dir)
        self.cfg, self.model_dir = cfg, model_dir
        self.strategy = strategy or make_strategy(cfg.train.peer_timeout_s, cfg.train.peer_join_timeout_s)
        self._cluster = cluster_tasks(self.strategy)  # None for one process
        self.data_service_address = data_service_address
        self._decode_options = pairs.decode_options(cfg)  # how a bad input record is re-read to name it
        self.is_chief, self._write_dir = _chief_and_write_dir(self.strategy, model_dir)
        self.log = log_fn if self.is_chief else (lambda s: log_fn(f"[worker] {s}"))
        if notice := loss_notice(self.train_files, cfg):
            self.log(notice)  # once, at start: the loss runs without a term its data lacks
        if cfg.data.num_frames > 2:
            self.log(_history_rule(cfg.data.num_frames) + "; the record job's summary counts them "
                     "(pairs_without_full_history)")
        self._stop_signal = None
        self._last_saved_step = None
        self._steps_done = 0  # the last step this process finished (the watchdog's message)
        self._heap_trimmed = False  # `_after_step`
        keras.utils.set_random_seed(cfg.train.seed)  # same initial weights for the same seed (reproducible runs)
        with self.strategy.scope():
            # model.compile=auto chooses for training; `plan` (default: the config's for training here) says how.
            self.model = build_model(cfg, job="train", plan=plan)
            self.optimizer = make_optimizer(cfg)
            self.optimizer.build(self.model.trainable_variables)
            self.global_step = tf.Variable(0, dtype=tf.int64, trainable=False, name="step")
            self.nonfinite_total = tf.Variable(0, dtype=tf.int64, trainable=False, name="nonfinite_total")
            self.nonfinite_in_row = tf.Variable(0, dtype=tf.int64, trainable=False, name="nonfinite_in_row")
        self.log(f"execution plan: {self.model.plan.describe()}")
        self.checkpoint = tf.train.Checkpoint(model=self.model, optimizer=self.optimizer, step=self.global_step,
                                              nonfinite_total=self.nonfinite_total,
                                              nonfinite_in_row=self.nonfinite_in_row)
        self.checkpoint_dir = os.path.join(model_dir, "checkpoints")  # the chief's: every worker restores from it
        self.manager = tf.train.CheckpointManager(self.checkpoint, os.path.join(self._write_dir, "checkpoints"),
                                                  max_to_keep=cfg.train.keep_checkpoints)
        # Forward + backward as one XLA program in compile mode "xla" (the model's stages inline), the reduction over
        # replicas and the update outside it; otherwise the model compiles its stages itself.
        xla = self.model.compile_mode == "xla"
        loss_and_grads = step_lib.loss_and_grads_fn(cfg, self.model, cfg.train.global_batch_size,
                                                    inline_stages=xla, on_variables=True)
        self._step_fn = step_lib.train_step_fn(
            cfg, tf.function(loss_and_grads, jit_compile=xla, reduce_retracing=True), all_reduce=_over_replicas)

    # -- steps -------------------------------------------------------------------------------------------------
    def _state_variables(self) -> step_lib.TrainState:
        """The variables that hold the training state: the model's and the Keras optimizer's own."""
        momentums, velocities = internals.adam_slots(self.optimizer)
        return step_lib.TrainState(list(self.model.trainable_variables), list(self.model.non_trainable_variables),
                                   momentums, velocities, self.optimizer.iterations)

    def _replica_step(self, batch) -> step_lib.StepResult:
        # This replica's copy of the state, read before the forward moves the BatchNorm variables.
        state = tf.nest.map_structure(lambda v: tf.identity(v.value), self._state_variables())
        return self._step_fn(state, batch)

    def step(self, iterator):
        """One training step on the next batch of `iterator` (a distributed iterator of `self.strategy`); returns the
        global batch's loss. A non-finite step changes no weight, BatchNorm statistic or optimizer slot (it is
        counted in `nonfinite_total` / `nonfinite_in_row`); `global_step` counts every step."""
        loss = self._step(iterator)
        self._after_step()
        return loss

    def _after_step(self) -> None:
        """After this process's first step: the memory that tracing and compiling the step freed goes back to the OS
        (`cpu.malloc_trim`). glibc keeps it otherwise, scattered between live blocks, under every later step's
        temporaries: the steady peak of a training job. Measured: docs/benchmarks.md, "The heap after compilation and
        huge pages"."""
        if not self._heap_trimmed:
            cpu.malloc_trim()
            self._heap_trimmed = True

    @tf.function
    def _step(self, iterator):
        result = self.strategy.run(self._replica_step, args=(next(iterator),))
        result = tf.nest.map_structure(lambda x: self.strategy.experimental_local_results(x)[0], result)
        self._assign_step_result(result)
        return result.loss

    def _assign_step_result(self, result: step_lib.StepResult) -> None:
        # Every replica computed the same new state from the reduced loss and gradients: replica 0's is assigned to
        # every copy (cross-replica context: each variable's assign updates all of its mirrored copies).
        for var, value in zip(tf.nest.flatten(self._state_variables()), tf.nest.flatten(result.state)):
            var.assign(value)
        skipped = tf.cast(tf.logical_not(result.finite), tf.int64)
        self.nonfinite_total.assign_add(skipped)
        self.nonfinite_in_row.assign((self.nonfinite_in_row + 1) * skipped)  # 0 after a finite step
        self.global_step.assign_add(1)

    @tf.function
    def _step_and_stop(self, iterator, stop_requested):
        """`step` plus the job-wide stop request (multi-worker): `stop_requested` (float64) is this worker's (0:
        none, else 2 ** its task number) and the returned sum over the workers, all-reduced inside the same step, is
        the bitmask of those that asked: every worker learns of a preemption at the same step."""
        result = self.strategy.run(self._replica_step, args=(next(iterator),))
        local_replicas = len(self.strategy.extended.worker_devices)
        stop_by = self.strategy.run(lambda s: replica_stop_requests(s, local_replicas), args=(stop_requested,))
        result = tf.nest.map_structure(lambda x: self.strategy.experimental_local_results(x)[0], result)
        self._assign_step_result(result)
        return result.loss, self.strategy.experimental_local_results(stop_by)[0]

    # -- loop --------------------------------------------------------------------------------------------------
    def _install_signal_handlers(self):
        def handler(signum, _frame):
            self._stop_signal = signum
        previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        return previous

    def restore_latest(self) -> str | None:
        """Restores the newest intact checkpoint of the chief's `model_dir` (damaged ones are moved aside); returns
        its prefix, or None for a fresh start."""
        resumed = restore_newest_intact(self.checkpoint, self.checkpoint_dir, self.log, move_damaged=self.is_chief)
        if resumed:
            self.log(f"resumed from {resumed} at step {int(self.global_step.numpy())}")
        return resumed

    def _input_iterator(self, start_step: int):
        """The distributed training input, positioned at `start_step` (`input.training_dataset`)."""
        cfg, global_batch = self.cfg, self.cfg.train.global_batch_size
        if global_batch % self.strategy.num_replicas_in_sync:
            raise ValueError(f"train.global_batch_size={global_batch} is not divisible by the "
                             f"{self.strategy.num_replicas_in_sync} replicas")

        def dataset_fn(ctx: tf.distribute.InputContext):
            return training_dataset(self.train_files, cfg, ctx.get_per_replica_batch_size(global_batch),
                                    shard=(ctx.num_input_pipelines, ctx.input_pipeline_id)
                                    if ctx.num_input_pipelines > 1 else None,
                                    # each step takes one batch per replica fed by this pipeline
                                    skip_batches=start_step * ctx.num_replicas_in_sync // ctx.num_input_pipelines,
                                    data_service_address=self.data_service_address)

        return iter(self.strategy.distribute_datasets_from_function(dataset_fn))

    def _log_step(self, writer, step: int, num_steps: int, loss_value: float, rate: float) -> None:
        eta = (num_steps - step) / max(rate, 1e-9)
        skipped = int(self.nonfinite_total.numpy())
        self.log(f"step {step}/{num_steps} loss {loss_value:.4f} {rate:.2f} steps/s "
                 f"ETA {int(eta // 60)}m{int(eta % 60):02d}s skipped_nonfinite {skipped}")
        with writer.as_default(step=step):
            tf.summary.scalar("loss", loss_value)
            tf.summary.scalar("learning_rate", float(self.optimizer.learning_rate.numpy()))
            tf.summary.scalar("steps_per_second", rate)
            tf.summary.scalar("skipped_nonfinite_steps", skipped)

    def _check_nonfinite(self, step: int) -> None:
        in_row = int(self.nonfinite_in_row.numpy())
        if in_row >= self.cfg.train.max_nonfinite_steps_in_row:
            self.manager.save(checkpoint_number=step)
            raise NonFiniteLossError(
                f"{in_row} non-finite steps in a row at step {step} (skipped, weights untouched; "
                f"{int(self.nonfinite_total.numpy())} in total). Check the input data and lower "
                f"train.learning_rate or set train.grad_clip_norm")

    def _finish(self, start_step: int, t_start: float, history: list) -> None:
        """Final checkpoint (unless this step has one), history, and the non-chief's temporary directory removed."""
        step = int(self.global_step.numpy())
        if self.manager.latest_checkpoint is None or not self.manager.latest_checkpoint.endswith(f"-{step}"):
            self._save(step)
        self.log(f"finished {step - start_step} steps in {time.time() - t_start:.1f} s; weights sha256 "
                 f"{weights_fingerprint(self.model)}")
        if self.is_chief:
            with tf.io.gfile.GFile(os.path.join(self.model_dir, "train_history.json"), "w") as f:
                json.dump({"loss": history}, f)
        self.remove_worker_dir()

    def remove_worker_dir(self) -> None:
        """A non-chief worker's temporary checkpoint directory goes once training ends (the chief has none)."""
        if not self.is_chief and tf.io.gfile.exists(self._write_dir):
            tf.io.gfile.rmtree(self._write_dir)

    def _save(self, step: int) -> str:
        """A checkpoint of the finished `step` (once per step)."""
        if self._last_saved_step != step:
            self.manager.save(checkpoint_number=step)
            self._last_saved_step = step
        return self.manager.latest_checkpoint

    def _peer_lost(self, err: BaseException | None, waited_s: float, step: int) -> PeerLostError:
        me, tasks = self._cluster
        reason = short_reason(err) if err is not None else f"step {step + 1} did not finish within " \
                                                              f"train.peer_timeout_s={self.cfg.train.peer_timeout_s:g} s"
        return lost_peer_error(lost_task(getattr(err, "message", "") or "", me, tasks), step, reason, waited_s,
                               self.checkpoint_dir)

    def _stop_request(self) -> float:
        """This worker's stop request for the next step: 0, or its `stop_request_bit` after SIGTERM/SIGINT."""
        return 0.0 if self._stop_signal is None else stop_request_bit(*self._cluster)

    def _run_step(self, iterator, watchdog, step: int) -> tuple[float, str | None]:
        """One step; returns (loss, the task whose stop request ends the job after this step, or None).

        Multi-worker: an error a lost peer causes becomes `PeerLostError`; nothing of the failed step is saved."""
        if self._cluster is None:
            try:
                with pairs.input_errors_named(self.train_files, self._decode_options):  # stops before any update
                    loss = self.step(iterator)
            except tf.errors.OutOfRangeError:
                raise self._no_batch(step) from None
            return float(loss.numpy()), None
        t0 = time.monotonic()
        if watchdog is not None:
            watchdog.arm()
        try:
            with pairs.input_errors_named(self.train_files, self._decode_options):
                loss, stop_by = self._step_and_stop(iterator, tf.constant(self._stop_request(), tf.float64))
                loss_value, stop_by = float(loss.numpy()), int(round(float(stop_by.numpy())))
            self._after_step()
        except tf.errors.OutOfRangeError:
            raise self._no_batch(step) from None
        except tf.errors.OpError as e:
            if not is_peer_error(e):
                raise
            raise self._peer_lost(e, time.monotonic() - t0, step) from None
        finally:
            if watchdog is not None:
                watchdog.disarm()
        return loss_value, (tasks_in_stop_mask(stop_by, self._cluster[1]) if stop_by else None)

    def _no_batch(self, step: int) -> ConfigError:
        """The error of a training input that ends (it repeats, so it never had a whole batch)."""
        history = f"; {_history_rule(self.cfg.data.num_frames)}" if self.cfg.data.num_frames > 2 else ""
        return ConfigError(f"the training input gave no batch at step {step}: the {len(self.train_files)} training "
                           f"files hold no example it can train on{history}")

    def train(self, num_steps: int | None = None) -> dict:
        """Runs (or resumes) training to `num_steps`: restore, input, steps with logging, checkpoints and the
        periodic evaluation, a checkpoint on SIGINT/SIGTERM.

        One process: a signal saves the finished step and returns `interrupted`. Several workers: a signal to any of
        them stops all after the same step, each saves it and returns `preempted`; a lost worker raises
        `PeerLostError` on the others (see the module docstring)."""
        cfg = self.cfg
        num_steps = cfg.train.num_steps if num_steps is None else num_steps
        previous = self._install_signal_handlers()  # early: a preemption during start-up stops after the first step
        watchdog = None
        try:
            self.restore_latest()  # before writing anything: a checkpoint of another config stops the run here
            if self.is_chief:
                tf.io.gfile.makedirs(self.model_dir)  # local or gs:// alike
                cfg.save(os.path.join(self.model_dir, "config.yaml"))
                plan_lib.save(self.model.plan, self.model_dir)
            start_step = self._steps_done = int(self.global_step.numpy())
            if start_step >= num_steps:
                self.log(f"already at step {start_step} >= {num_steps}; nothing to do")
                self.remove_worker_dir()
                return {"step": start_step}
            iterator = self._input_iterator(start_step)
            writer = (tf.summary.create_file_writer(os.path.join(self.model_dir, "train")) if self.is_chief
                      else tf.summary.create_noop_writer())
            t_start, last_log_t, last_log_step = time.time(), time.time(), start_step
            loss_value, history = float("nan"), []
            while int(self.global_step.numpy()) < num_steps:
                step_before = int(self.global_step.numpy())
                loss_value, stop_by = self._run_step(iterator, watchdog, step_before)
                if self._cluster is not None and watchdog is None:  # from the second step on: the first compiles
                    watchdog = Watchdog(cfg.train.peer_timeout_s,
                                        lambda waited: str(self._peer_lost(None, waited, self._steps_done)))
                step = self._steps_done = int(self.global_step.numpy())
                self._check_nonfinite(step)
                if step % cfg.train.log_every_steps == 0 or step == num_steps:
                    now = time.time()
                    self._log_step(writer, step, num_steps, loss_value, (step - last_log_step) / max(now - last_log_t,
                                                                                                     1e-9))
                    last_log_t, last_log_step = now, step
                    history.append((step, loss_value))
                if step % cfg.train.checkpoint_every_steps == 0:
                    self._save(step)
                if (self.is_chief and self.val_files and cfg.train.eval_every_steps
                        and step % cfg.train.eval_every_steps == 0):
                    self.evaluate_subset(step)
                if stop_by is not None and step < num_steps:
                    path = self._save(step)
                    self.log(f"preempted at step {step} (signal to {stop_by}); every worker saved step {step}"
                             + (f", checkpoint {path}" if self.is_chief else "")
                             + f"; exit status {EXIT_PREEMPTED}: run the same commands again to resume")
                    self.remove_worker_dir()
                    writer.flush()
                    return {"step": step, "loss": loss_value, "interrupted": True, "preempted": True,
                            "stopped_by": stop_by}
                if self._cluster is None and self._stop_signal is not None:
                    path = self._save(step)
                    self.log(f"interrupted by signal {self._stop_signal} at step {step}; checkpoint {path}; "
                             f"run the same command again to resume")
                    return {"step": step, "loss": loss_value, "interrupted": True}
            self._finish(start_step, t_start, history)
        except tf.errors.OpError as e:  # outside a step (restore, input, a checkpoint): no step is in flight
            if self._cluster is None or not is_peer_error(e):
                raise
            raise self._peer_lost(e, 0.0, self._steps_done) from None
        finally:
            if watchdog is not None:
                watchdog.close()
            for s, h in previous.items():
                signal.signal(s, h)
        return {"step": int(self.global_step.numpy()), "loss": loss_value, "interrupted": False}

    def evaluate_subset(self, step: int) -> dict:
        """The periodic evaluation: `evaluation.evaluate` of the model on the first `train.eval_num_batches`
        validation pairs, its headline numbers written to TensorBoard (`evaluation.write_summaries`)."""
        cfg = self.cfg
        result, _ = evaluate(cfg, self.val_files, ModelPredictor(self.model, cfg.model.jit_compile),
                             max_pairs=cfg.train.eval_num_batches, log_fn=None)
        write_summaries(os.path.join(self.model_dir, "eval"), step, result)
        self.log(f"eval@{step}: all/moving {result['all/moving/mean_l2_mps']:.3f} m/s, all/stationary "
                 f"{result['all/stationary/mean_l2_mps']:.3f} m/s")
        return result

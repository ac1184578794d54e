"""Train FastFlow3D: python tools/train.py --config configs/synthetic_cpu.yaml --data_dir D --model_dir M

Several GPUs of one machine: nothing to add (MirroredStrategy). Several machines: set TF_CONFIG on each worker (see
README, "Training on several GPUs and machines"). Input on other machines: --data_service_address
(tools/data_service.py).

Exit status: 0 done; 1 an error (a one-line message), or one process interrupted by SIGINT/SIGTERM (checkpoint
written: run the same command again); 69 a multi-worker job lost a worker (restart every worker with the same
command); 75 preempted: SIGTERM/SIGINT to any worker of a multi-worker job, every worker saved the same step (run the
same commands again). See README, "Faults and preemption".
"""
import os
import sys

import _common


def main():
    _common.start("train")  # before TensorFlow is imported
    from ff3d_tf.data.pairs import list_segment_files
    from ff3d_tf.training.cluster import EXIT_PEER_LOST, EXIT_PREEMPTED, PeerLostError
    from ff3d_tf.training.input import training_files
    from ff3d_tf.training.trainer import Trainer
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--data_dir", required=True, help="directory (or glob) of training segment TFRecords")
    p.add_argument("--val_dir", default=None, help="validation records for the periodic metric subset")
    p.add_argument("--model_dir", required=True, help="checkpoints, TensorBoard logs, resolved config; resumes")
    p.add_argument("--data_service_address", default=None,
                   help="grpc://host:port of a tf.data service dispatcher (tools/data_service.py): decoding and "
                        "pairing run on its workers")
    args = p.parse_args()
    cfg = _common.load(args)
    train_files = training_files(list_segment_files(args.data_dir), cfg)  # data.max_training_segments applied
    val_files = list_segment_files(args.val_dir) if args.val_dir else []
    print(f"training on {len(train_files)} segment files; model_dir {args.model_dir}", flush=True)
    try:
        # Held until exit: tearing a multi-worker strategy down takes seconds, which the os._exit below skips.
        trainer = Trainer(cfg, args.model_dir, train_files, val_files, log_fn=lambda s: print(s, flush=True),
                          data_service_address=args.data_service_address)
        result = trainer.train()
    except PeerLostError as e:
        # One line, no traceback; os._exit: after a lost peer, TensorFlow's shutdown can wait on it at exit.
        print(f"error: {e}", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(EXIT_PEER_LOST)
    if result.get("preempted"):
        print(f"preempted at step {result['step']} (checkpoint written by every worker); exit status "
              f"{EXIT_PREEMPTED}: run the same commands again to resume", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(EXIT_PREEMPTED)  # every file is written; TensorFlow's shutdown would only add seconds
    if result.get("interrupted"):  # a non-zero status, so `train && eval` never evaluates an unfinished run
        sys.exit(f"interrupted at step {result['step']} (checkpoint written); run the same command to resume")


if __name__ == "__main__":
    _common.run(main)

"""tf.data service roles for the training input: decoding and pairing on machines other than the trainers'.

python tools/data_service.py --dispatcher --port 5050 [--work_dir gs://bucket/dispatcher]
python tools/data_service.py --worker --dispatcher_address host:5050 [--port 5051] [--host this-machine]
python tools/train.py ... --data_service_address grpc://host:5050

Workers need the segment files at the same paths as the trainers (a shared filesystem or gs://). Each role serves
until it is stopped (Ctrl-C / SIGTERM): it stops its server and exits with status 0, or, when the server still waits
on a client's request after --stop_timeout_s, leaves it and exits with status 1 (a worker's splits go to the other
workers; a dispatcher with --work_dir has journalled its state before answering). With --work_dir the dispatcher
is fault-tolerant: restart it with the same --port and --work_dir and training goes on (docs/training.md, "Faults and
preemption"); a killed worker can be restarted at any time (any port), and training goes on meanwhile.
"""
import argparse
import faulthandler
import os
import signal
import sys
import time

import _common  # noqa: F401  (sets up the import path and TF logging)


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.training.data_service import start_dispatcher, start_worker
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    role = p.add_mutually_exclusive_group(required=True)
    role.add_argument("--dispatcher", action="store_true", help="run the dispatcher")
    role.add_argument("--worker", action="store_true", help="run a worker")
    p.add_argument("--port", type=int, default=0, help="port to listen on (0: any free port, printed)")
    p.add_argument("--dispatcher_address", help="host:port of the dispatcher (workers)")
    p.add_argument("--work_dir", default=None, help="dispatcher state, so a restarted dispatcher resumes its jobs")
    p.add_argument("--host", default=None, help="worker: the host name trainers reach it by (default localhost)")
    p.add_argument("--stop_timeout_s", type=float, default=10.0,
                   help="on Ctrl-C / SIGTERM, the longest wait for the server to stop before leaving it (status 1)")
    args = p.parse_args()
    if args.worker and not args.dispatcher_address:
        sys.exit("--worker needs --dispatcher_address host:port")
    if not args.stop_timeout_s > 0:
        sys.exit(f"--stop_timeout_s={args.stop_timeout_s}: must be > 0")
    server = (start_dispatcher(args.port, args.work_dir) if args.dispatcher
              else start_worker(args.dispatcher_address, args.port, args.host))
    role_name = "dispatcher" if args.dispatcher else "worker"
    print(f"{role_name} serving on port {server.port}"
          + (f"; trainers use --data_service_address {server.target}" if args.dispatcher else ""), flush=True)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM stops the server as Ctrl-C does
    try:
        while True:  # not server.join(): a blocking C++ call would keep Python's signal handling (Ctrl-C) waiting
            time.sleep(1.0)
    except KeyboardInterrupt:
        print(f"{role_name}: stopping; if the server still waits on a client's request after "
              f"{args.stop_timeout_s:g} s, the process leaves it and exits with status 1", file=sys.stderr, flush=True)
        # TensorFlow's stop can wait without end on a request in flight (its gRPC server shuts down without a
        # deadline) and holds the GIL meanwhile, so no Python thread could bound it: faulthandler's watchdog, a C
        # thread, ends the process (status 1) after the timeout, its thread dump going nowhere.
        with open(os.devnull, "w") as nowhere:
            faulthandler.dump_traceback_later(args.stop_timeout_s, exit=True, file=nowhere)
            server.stop()
            faulthandler.cancel_dump_traceback_later()


if __name__ == "__main__":
    main()

"""tf.data service roles for the training input: decoding and pairing on machines other than the trainers'.

python tools/data_service.py --dispatcher --port 5050 [--work_dir gs://bucket/dispatcher]
python tools/data_service.py --worker --dispatcher_address host:5050 [--port 5051] [--host this-machine]
python tools/train.py ... --data_service_address grpc://host:5050

Workers need the segment files at the same paths as the trainers (a shared filesystem or gs://). Each role serves
until it is stopped (Ctrl-C / SIGTERM: it stops its server and exits with status 0). With --work_dir the dispatcher
is fault-tolerant: restart it with the same --port and --work_dir and training goes on (docs/training.md, "Faults and
preemption"); a killed worker can be restarted at any time (any port), and training goes on meanwhile.
"""
import argparse
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
    args = p.parse_args()
    if args.worker and not args.dispatcher_address:
        sys.exit("--worker needs --dispatcher_address host:port")
    server = (start_dispatcher(args.port, args.work_dir) if args.dispatcher
              else start_worker(args.dispatcher_address, args.port, args.host))
    print(f"{'dispatcher' if args.dispatcher else 'worker'} serving on port {server.port}"
          + (f"; trainers use --data_service_address {server.target}" if args.dispatcher else ""), flush=True)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM stops the server as Ctrl-C does
    try:
        while True:  # not server.join(): a blocking C++ call would keep Python's signal handling (Ctrl-C) waiting
            time.sleep(1.0)
    except KeyboardInterrupt:
        server.stop()


if __name__ == "__main__":
    main()

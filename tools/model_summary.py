"""Parameter count of each row of the paper's architecture table; the last line is `total_params <n>`.

With `--set model.head=gru`, rows W-Z are DeFlow's GRU point decoder: W (each point takes its pillar's cells), then
the head's layers: GRU-x (the offset encoding), GRU-z, GRU-r, GRU-q (update gate, reset gate, candidate), MLP-1,
MLP-2 (see docs/architecture.md).

python tools/model_summary.py --config configs/fastflow3d_waymo.yaml [--set model.head=gru]
"""
import _common


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.model import build_model
    args = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml").parse_args()
    cfg = _common.load(args)
    model = build_model(cfg)
    head = "paper" if cfg.model.head == "paper" else f"gru, {cfg.model.gru_iterations} iterations"
    print(f"FastFlow3D, grid {cfg.grid.num_pillars_x} x {cfg.grid.num_pillars_y}, head {head}")
    for row, count in model.table_rows():
        print(f"{row:>5} {count:>10,d}")
    print(f"total_params {model.count_params()}")


if __name__ == "__main__":
    main()

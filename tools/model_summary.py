"""Parameter count of each row of the paper's architecture table; the last line is `total_params <n>`.

python tools/model_summary.py --config configs/fastflow3d_waymo.yaml
"""
import _common

from ff3d_tf.model import build_model


def main():
    args = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml").parse_args()
    cfg = _common.load(args)
    model = build_model(cfg)
    print(f"FastFlow3D, grid {cfg.grid.num_pillars_x} x {cfg.grid.num_pillars_y}")
    for row, count in model.table_rows():
        print(f"{row:>4} {count:>10,d}")
    print(f"total_params {model.count_params()}")


if __name__ == "__main__":
    main()

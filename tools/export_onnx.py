"""Export a checkpoint's serving forward as ONNX (dynamic point counts), for ONNX Runtime or TensorRT:

python tools/export_onnx.py --config C --checkpoint M --out model.onnx [--variant loop|single_chunk]
    [--pose_inputs world_float64|relative_float32] [--opset 17]

`loop` (default): the point encoder in chunks (ONNX Loop), poses as float64 inputs, for ONNX Runtime. `single_chunk`:
no Loop and, by default, the float32 relative transform t0_from_tm1 as input (no float64), for TensorRT 10 (which runs
ScatterElements with reduction add as a plugin). See ff3d_tf/inference/onnx_export.py. The file carries the config
(with the order of the sweeps its model reads) in its metadata: the tools given it load that config.
"""
import json

import _common


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.checkpoints import restore_model
    from ff3d_tf.inference import onnx_export
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--checkpoint", required=True, help="model_dir or checkpoint prefix")
    p.add_argument("--out", required=True, help="the .onnx file to write")
    p.add_argument("--variant", default="loop", choices=onnx_export.VARIANTS)
    p.add_argument("--pose_inputs", default=None, choices=onnx_export.POSE_INPUTS,
                   help="default: world_float64 for loop, relative_float32 for single_chunk")
    p.add_argument("--opset", type=int, default=onnx_export.DEFAULT_OPSET)
    args = p.parse_args()
    cfg = _common.load(args)
    model = restore_model(cfg, args.checkpoint)
    info = onnx_export.export_onnx(model, args.out, args.variant, args.pose_inputs, args.opset, cfg=cfg)
    print(json.dumps(info, indent=1))
    print(f"wrote {args.out} ({info['variant']}, inputs {', '.join(info['inputs'])})")


if __name__ == "__main__":
    _common.run(main)

"""ONNX export (ff3d_tf/inference/onnx_export.py): onnxruntime against TensorFlow's serving forward, NaN points,
empty clouds, determinism with 2 threads, the graph's ops, the conversion handlers against NumPy, the loop-free
point encoder (ops.ONE_CHUNK) and tools/export_onnx.py; both variants with DeFlow's GRU head (model.head=gru) and
DeltaFlow's point head (model.head=mlp)."""
import subprocess
import sys

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import tensorflow as tf
import tf2onnx
from onnx import TensorProto, helper

from ff3d_tf.inference import onnx_export as ox
from ff3d_tf.inference.saved_model import FlowServingModule
from ff3d_tf.model import build_model, ops

# Ops of the single_chunk graph (tiny config; the paper config's graph has the same ops): what TensorRT must run.
# ScatterElements with reduction add is TensorRT 10's ScatterElements plugin; the rest are TensorRT layers.
SINGLE_CHUNK_OPS = {
    "Add", "And", "Cast", "Concat", "ConstantOfShape", "Conv", "Equal", "Expand", "Floor", "Gather", "Greater",
    "GreaterOrEqual", "IsInf", "IsNaN", "Less", "LessOrEqual", "MatMul", "Max", "Min", "Mul", "Not", "Or", "Pad",
    "Range", "ReduceSum", "Relu", "Reshape", "ScatterElements", "ScatterND", "Shape", "Slice", "Split",
    "Squeeze", "Sub", "Sum", "Transpose", "Unsqueeze", "Where"}


def _pose(yaw, x, y):
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[:3, 3] = [x, y, 1.5]
    return m


POSE_TM1, POSE_T0 = _pose(0.40, 1000.0, -700.0), _pose(0.43, 1001.1, -699.6)  # 1 km from the world origin


def _cloud(rng, n, xy=45.0):
    """[n,5] float32: x, y uniform in +-xy (the tiny grid is +-40 m, so some fall outside), z in +-3.5 (grid +-3),
    features in [0, 1]."""
    pts = np.concatenate([rng.uniform(-xy, xy, (n, 2)), rng.uniform(-3.5, 3.5, (n, 1)), rng.uniform(0, 1, (n, 2))],
                         -1)
    return pts.astype(np.float32)


def _session_options(threads):
    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    return options


@pytest.fixture(scope="module")
def exported(tiny_config, tmp_path_factory):
    """The tiny model, its TensorFlow serving function and both exports: "loop" written by tools/export_onnx.py
    from a checkpoint, "single_chunk" by `export_onnx` in this process."""
    from conftest import ROOT, TINY_OVERRIDES
    tmp = tmp_path_factory.mktemp("onnx")
    model = build_model(tiny_config)
    prefix = tf.train.Checkpoint(model=model).save(str(tmp / "model" / "ckpt"))
    sets = [a for s in TINY_OVERRIDES for a in ("--set", s)]
    tool = subprocess.Popen([sys.executable, "tools/export_onnx.py", "--config", "", *sets, "--checkpoint", prefix,
                             "--out", str(tmp / "loop.onnx")], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    info = ox.export_onnx(model, str(tmp / "single_chunk.onnx"), "single_chunk")  # while the tool runs
    stdout, stderr = tool.communicate(timeout=600)
    assert tool.returncode == 0, stderr[-3000:]
    assert f"wrote {tmp / 'loop.onnx'} (loop, inputs points_tm1, points_t0, pose_tm1, pose_t0)" in stdout
    module = FlowServingModule(model, tiny_config.data.point_bucket_base, jit_compile=False)
    return {"model": model, "module": module, "info": info,
            "paths": {"loop": str(tmp / "loop.onnx"), "single_chunk": str(tmp / "single_chunk.onnx")}}


def _tensorflow(module, pts1, pts0):
    out = module.serve(tf.constant(pts1), tf.constant(pts0), tf.constant(POSE_TM1), tf.constant(POSE_T0))
    return out["flow_mps"].numpy(), out["point_valid"].numpy()


@pytest.mark.parametrize("variant", ox.VARIANTS)
def test_onnxruntime_matches_tensorflow(exported, variant):
    predictor = ox.OnnxFlowPredictor(exported["paths"][variant], intra_op_threads=2)
    assert predictor.pose_inputs == ox.DEFAULT_POSE_INPUTS[variant]
    rng = np.random.default_rng(3)
    # 70,000 and 140,000 points: two and three turns of the loop variant's chunk loop (ops.POINT_CHUNK = 65,536).
    for n0, n1 in ((700, 650), (40, 900), (0, 30), (25, 0), (0, 0), (70000, 140000)):
        pts0, pts1 = _cloud(rng, n0), _cloud(rng, n1)
        bad0 = np.arange(n0) % 9 == 4  # NaN or Inf in a coordinate or a feature
        for col, value in ((0, np.nan), (2, np.inf), (4, np.nan)):
            pts0[bad0 & (np.arange(n0) % 3 == col % 3), col] = value
        pts1[np.arange(n1) % 11 == 2, 1] = np.nan
        flow_tf, valid_tf = _tensorflow(exported["module"], pts1, pts0)
        out = predictor(pts1, pts0, POSE_TM1, POSE_T0)
        flow, valid = out["flow_mps"], out["point_valid"]
        assert flow.shape == (n0, 3) and flow.dtype == np.float32 and valid.shape == (n0,) and valid.dtype == bool
        np.testing.assert_array_equal(valid, valid_tf)
        assert np.isfinite(flow).all()  # a NaN point leaks no NaN
        np.testing.assert_array_equal(flow[~valid], 0.0)  # masked points: flow exactly 0, as TensorFlow
        assert not valid[bad0].any()
        if n0:  # float32 rounding of the pillar sums: ~70 points per pillar at 140,000 points give flows ~500 m/s
            np.testing.assert_allclose(flow, flow_tf, atol=1e-4 + 4e-6 * np.abs(flow_tf).max(), rtol=0)
        if n0 > 100:  # a real test: many valid and invalid points, flows of metres per second
            assert 0.3 * n0 < valid.sum() < 0.95 * n0 and np.abs(flow_tf).max() > 1.0


@pytest.mark.parametrize("variant", ox.VARIANTS)
def test_repeated_calls_with_two_threads_are_identical(exported, variant):
    predictor = ox.OnnxFlowPredictor(exported["paths"][variant], intra_op_threads=2)
    rng = np.random.default_rng(4)
    pts0, pts1 = _cloud(rng, 3000, 30.0), _cloud(rng, 3000, 30.0)  # ~3 points per pillar: sums of many terms
    first = predictor(pts1, pts0, POSE_TM1, POSE_T0)
    for _ in range(3):
        again = predictor(pts1, pts0, POSE_TM1, POSE_T0)
        np.testing.assert_array_equal(again["flow_mps"], first["flow_mps"])
        np.testing.assert_array_equal(again["point_valid"], first["point_valid"])


def _all_nodes(proto):
    return [n for g in ox._graphs(proto.graph) for n in g.node]


def test_graph_ops(exported):
    loop, single = (onnx.load(exported["paths"][v]) for v in ox.VARIANTS)
    for proto in (loop, single):
        assert {d for d, _ in ox.graph_ops(proto)} == {""}  # the standard domain only
        nodes = _all_nodes(proto)
        scatters = [n for n in nodes if n.op_type == "ScatterElements"]
        assert scatters and all(helper.get_attribute_value(a) == b"add" for n in scatters for a in n.attribute
                                if a.name == "reduction")
        assert not [n for n in nodes if n.op_type == "ScatterND" and any(a.name == "reduction" for a in n.attribute)]
        assert "UnsortedSegmentSum" not in {n.op_type for n in nodes}
        assert {o.domain: o.version for o in proto.opset_import}[""] == ox.DEFAULT_OPSET
    assert ("", "Loop") in ox.graph_ops(loop)
    single_ops = {op for _, op in ox.graph_ops(single)}
    assert single_ops == SINGLE_CHUNK_OPS, (single_ops - SINGLE_CHUNK_OPS, SINGLE_CHUNK_OPS - single_ops)
    assert set(exported["info"]["ops"]) == SINGLE_CHUNK_OPS
    # No float64 anywhere in the single_chunk graph (TensorRT has none); the loop graph takes float64 poses.
    assert [i.type.tensor_type.elem_type for i in single.graph.input] == [TensorProto.FLOAT] * 3
    assert not [n for n in _all_nodes(single) if n.op_type == "Cast" and
                helper.get_attribute_value(n.attribute[0]) == TensorProto.DOUBLE]
    loop_inputs = [i.type.tensor_type.elem_type for i in loop.graph.input]
    assert loop_inputs == [TensorProto.FLOAT] * 2 + [TensorProto.DOUBLE] * 2


def _model(nodes, inputs=("x",), outputs=("y",), opset=17):
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in inputs],
                              [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in outputs])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])


def test_check_graph_rejects_what_does_not_port():
    scatter_nd = _model([helper.make_node("ScatterND", ["x", "i", "u"], ["y"], reduction="add")])
    with pytest.raises(ValueError, match="ScatterND with reduction"):
        ox.check_graph(scatter_nd, "loop", "world_float64")
    with pytest.raises(ValueError, match="of domain 'ai.onnx.contrib'"):
        ox.check_graph(_model([helper.make_node("Foo", ["x"], ["y"], domain="ai.onnx.contrib")]), "loop",
                       "world_float64")
    with pytest.raises(ValueError, match="UnsortedSegmentSum is no ONNX op"):
        ox.check_graph(_model([helper.make_node("UnsortedSegmentSum", ["x"], ["y"])]), "loop", "world_float64")
    body = helper.make_graph([helper.make_node("Identity", ["c"], ["c_out"])], "body", [], [])
    loop = _model([helper.make_node("Loop", ["n", "c"], ["y"], body=body)])
    with pytest.raises(ValueError, match="Loop in the single_chunk graph"):
        ox.check_graph(loop, "single_chunk", "relative_float32")
    cast64 = _model([helper.make_node("Cast", ["x"], ["y"], to=TensorProto.DOUBLE)])
    with pytest.raises(ValueError, match="float64 Cast"):
        ox.check_graph(cast64, "single_chunk", "relative_float32")
    with pytest.raises(ValueError, match=r"inputs \['x'\], expected \['points_tm1', 'points_t0', 't0_from_tm1'\]"):
        ox.check_graph(_model([helper.make_node("Identity", ["x"], ["y"])]), "single_chunk", "relative_float32")
    with pytest.raises(ValueError, match="opset=15: needs >= 16"):
        ox.convert(None, "loop", opset=15)
    with pytest.raises(ValueError, match="variant='onnx': one of loop, single_chunk"):
        ox.convert(None, "onnx")


def _run(proto, feeds, threads=2):
    return ort.InferenceSession(proto.SerializeToString(), _session_options(threads),
                                providers=["CPUExecutionProvider"]).run(None, feeds)


def test_segment_sum_handler_matches_numpy():
    num_segments = 7

    @tf.function
    def segment_sum(values, ids):
        return tf.math.unsorted_segment_sum(values, ids, num_segments)

    proto = ox.convert_function(segment_sum, [tf.TensorSpec([None, 4], tf.float32, name="values"),
                                              tf.TensorSpec([None], tf.int32, name="ids")])
    assert {op for _, op in ox.graph_ops(proto)} >= {"ScatterElements"}
    assert not {op for _, op in ox.graph_ops(proto)} & {"ScatterND", "UnsortedSegmentSum"}
    rng = np.random.default_rng(0)
    session = ort.InferenceSession(proto.SerializeToString(), _session_options(2), providers=["CPUExecutionProvider"])
    for p in (0, 1, 50, 20000):
        values = rng.normal(size=(p, 4)).astype(np.float32)
        values[::13] = np.nan  # on ids outside the segments only (set below): TensorFlow drops those
        ids = rng.integers(-3, num_segments + 3, p).astype(np.int32)  # -3..-1 and 7..9: no segment
        ids[::13] = -1
        expected = np.zeros((num_segments, 4))
        inside = (ids >= 0) & (ids < num_segments)
        np.add.at(expected, ids[inside], values[inside].astype(np.float64))
        (got,) = session.run(None, {"values": values, "ids": ids})
        assert got.shape == (num_segments, 4)
        np.testing.assert_allclose(got, expected, atol=1e-3, rtol=1e-5)
        for _ in range(2):  # the same bits on every call (2 threads)
            np.testing.assert_array_equal(session.run(None, {"values": values, "ids": ids})[0], got)
        if 0 < p < 1000:  # and TensorFlow's own sum where TensorFlow accepts the ids (CPU: no id >= num_segments)
            ok = ids < num_segments
            np.testing.assert_allclose(got - segment_sum(values[ok], ids[ok]).numpy(), 0, atol=1e-5)


def test_select_handler_keeps_nan_out():
    @tf.function
    def select(x, rows):
        masked = tf.where(tf.math.is_finite(x) & (x > -10.0), 2.0 * x, tf.zeros_like(x))  # SelectV2
        picked = tf.raw_ops.Select(condition=rows, x=masked, y=-tf.ones_like(masked))  # Select with a 1-D condition
        return masked, picked

    proto = ox.convert_function(select, [tf.TensorSpec([None, 2], tf.float32, name="x"),
                                         tf.TensorSpec([None], tf.bool, name="rows")])
    x = np.array([[1.0, np.nan], [np.inf, -np.inf], [3.0, -20.0]], np.float32)
    rows = np.array([True, False, True])
    masked, picked = _run(proto, {"x": x, "rows": rows})
    np.testing.assert_array_equal(masked, [[2.0, 0.0], [0.0, 0.0], [6.0, 0.0]])  # tf2onnx's arithmetic gives NaN
    np.testing.assert_array_equal(picked, [[2.0, 0.0], [-1.0, -1.0], [6.0, 0.0]])


def test_predictor_rejects_bad_input(exported, tmp_path):
    path = exported["paths"]["loop"]
    predictor = ox.OnnxFlowPredictor(path)
    pts = np.zeros((4, 5), np.float32)
    with pytest.raises(ValueError, match=r"input points_t0 must be float32 \[N, 5\], got float64 \[4, 5\]"):
        predictor(pts, pts.astype(np.float64), POSE_TM1, POSE_T0)
    with pytest.raises(ValueError, match=r"input points_tm1 must be float32 \[N, 5\], got float32 \[4, 3\]"):
        predictor(pts[:, :3], pts, POSE_TM1, POSE_T0)
    with pytest.raises(ValueError, match=r"input pose_tm1 must be float64 \[4, 4\]"):
        predictor(pts, pts, POSE_TM1.astype(np.float32), POSE_T0)
    with pytest.raises(ValueError, match="pose_t0 must be rigid"):
        predictor(pts, pts, POSE_TM1, 2.0 * POSE_T0 * np.r_[np.ones(3), 0.5][:, None])
    with pytest.raises(ValueError, match="pose_tm1 must be finite"):
        predictor(pts, pts, np.full((4, 4), np.nan), POSE_T0)
    plain = tmp_path / "plain.onnx"  # an ONNX file of another origin
    onnx.save(_model([helper.make_node("Identity", ["x"], ["y"])]), str(plain))
    with pytest.raises(ValueError, match="not written by ff3d_tf's ONNX export"):
        ox.OnnxFlowPredictor(str(plain))


def test_export_twin_is_the_same_model_without_xla(exported):
    model = exported["model"]
    for variant, chunk in (("loop", ops.POINT_CHUNK), ("single_chunk", ops.ONE_CHUNK)):
        twin = ox.export_twin(model, variant)
        assert twin.compile_mode == "none" and twin.point_encoder.chunk_size == chunk
        assert len(twin.weights) == len(model.weights)
        for a, b in zip(twin.weights, model.weights):
            np.testing.assert_array_equal(a.numpy(), b.numpy())


def test_one_chunk_runs_without_a_loop_at_any_point_count():
    weights = [tf.constant([[1.0, -2.0], [0.5, 3.0]])]

    def encode(points, valid, w):  # a chunk's values and rows
        values = tf.nn.relu(tf.matmul(points, w[0]))
        return tf.where(valid[:, None], values, 0.0), values[:, :1]

    spec = [tf.TensorSpec([None, 2], tf.float32), tf.TensorSpec([None], tf.bool), tf.TensorSpec([None], tf.int32)]
    functions = {chunk: tf.function(lambda p, v, i, chunk=chunk: ops.chunked_segment_sum(encode, p, v, weights, i, 5,
                                                                                         chunk), input_signature=spec)
                 for chunk in (ops.ONE_CHUNK, 3)}
    graphs = {chunk: f.get_concrete_function().graph.as_graph_def() for chunk, f in functions.items()}
    loops = {chunk: [n.op for n in g.node if "While" in n.op] for chunk, g in graphs.items()}
    assert loops[ops.ONE_CHUNK] == [] and loops[3]
    rng = np.random.default_rng(1)
    for n in (0, 1, 10):
        points = rng.normal(size=(n, 2)).astype(np.float32)
        valid, ids = rng.uniform(size=n) < 0.8, rng.integers(-1, 5, n).astype(np.int32)
        values = np.maximum(points @ weights[0].numpy(), 0) * valid[:, None]
        expected = np.zeros((5, 2))
        np.add.at(expected, ids[ids >= 0], values[ids >= 0])
        for f in functions.values():
            sums, rows = f(points, valid, ids)
            np.testing.assert_allclose(sums.numpy(), expected, atol=1e-5)
            np.testing.assert_allclose(rows.numpy(), np.maximum(points @ weights[0].numpy(), 0)[:, :1], atol=1e-6)


@pytest.mark.slow
def test_paper_model_at_32k_points(tmp_path):
    """The paper's model (random weights) at 32,000 points: onnxruntime (loop variant, 2 threads) within 1e-3 m/s
    of TensorFlow's serving forward (the config's compile mode), the same validity, the same bits on a second call."""
    from ff3d_tf.config import load_config
    from conftest import ROOT
    cfg = load_config(f"{ROOT}/configs/fastflow3d_waymo.yaml", [])
    model = build_model(cfg)
    path = str(tmp_path / "paper.onnx")
    ox.export_onnx(model, path, "loop")
    rng = np.random.default_rng(7)
    pts0, pts1 = _cloud(rng, 32000, 90.0), _cloud(rng, 32000, 90.0)  # the grid is +-85 m
    pts0[::97, 1] = np.nan
    module = FlowServingModule(model, cfg.data.point_bucket_base, cfg.model.jit_compile)
    flow_tf, valid_tf = _tensorflow(module, pts1, pts0)
    predictor = ox.OnnxFlowPredictor(path, intra_op_threads=2)
    out = predictor(pts1, pts0, POSE_TM1, POSE_T0)
    np.testing.assert_array_equal(out["point_valid"], valid_tf)
    assert valid_tf.sum() > 20000 and np.abs(flow_tf).max() > 1.0
    np.testing.assert_allclose(out["flow_mps"], flow_tf, atol=1e-3, rtol=0)
    np.testing.assert_array_equal(out["flow_mps"][~valid_tf], 0.0)
    np.testing.assert_array_equal(predictor(pts1, pts0, POSE_TM1, POSE_T0)["flow_mps"], out["flow_mps"])


# -- the GRU head (model.head=gru) ----------------------------------------------------------------------------------

# The GRU head adds its gates' and GELU's activations; it writes no chunk rows (ScatterND) and clips no cell index
# from above (Min: the paper head's ungrid).
GRU_SINGLE_CHUNK_OPS = (SINGLE_CHUNK_OPS - {"Min", "ScatterND"}) | {"Erf", "Sigmoid", "Tanh"}


@pytest.fixture(scope="module")
def exported_gru(tiny_config, tmp_path_factory):
    """The tiny model with DeFlow's GRU head, its TensorFlow serving function and both exports; the loop variant with
    256-point chunks (`ops.POINT_CHUNK` patched for the export), so that a few hundred points take several turns of
    the encoder's and the head's loops."""
    from ff3d_tf.config import replace_config
    cfg = replace_config(tiny_config, {"model.head": "gru"})
    tmp = tmp_path_factory.mktemp("onnx_gru")
    model = build_model(cfg)
    paths = {v: str(tmp / f"{v}.onnx") for v in ox.VARIANTS}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ops, "POINT_CHUNK", 256)
        assert ox.export_twin(model, "loop").head_gru.chunk_size == 256
        ox.export_onnx(model, paths["loop"], "loop")
    info = ox.export_onnx(model, paths["single_chunk"], "single_chunk")
    module = FlowServingModule(model, cfg.data.point_bucket_base, jit_compile=False)
    return {"model": model, "module": module, "info": info, "paths": paths}


@pytest.fixture(scope="module")
def exported_mlp(tiny_config, tmp_path_factory):
    """The tiny model with DeltaFlow's point head (its BatchNorm's moving statistics moved off their initial values)
    and both exports, as `exported_gru`."""
    from ff3d_tf.config import replace_config
    cfg = replace_config(tiny_config, {"model.head": "mlp"})
    tmp = tmp_path_factory.mktemp("onnx_mlp")
    model = build_model(cfg)
    model.head_mlp.norm.moving_mean.assign(np.linspace(-0.3, 0.3, model.head_mlp.units).astype(np.float32))
    model.head_mlp.norm.moving_variance.assign(np.linspace(0.5, 2.0, model.head_mlp.units).astype(np.float32))
    paths = {v: str(tmp / f"{v}.onnx") for v in ox.VARIANTS}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ops, "POINT_CHUNK", 256)
        ox.export_onnx(model, paths["loop"], "loop")
    info = ox.export_onnx(model, paths["single_chunk"], "single_chunk")
    module = FlowServingModule(model, cfg.data.point_bucket_base, jit_compile=False)
    return {"model": model, "module": module, "info": info, "paths": paths}


@pytest.mark.parametrize("head", ["gru", "mlp"])
@pytest.mark.parametrize("variant", ox.VARIANTS)
def test_other_heads_onnxruntime_match_tensorflow(exported_gru, exported_mlp, head, variant):
    exported = {"gru": exported_gru, "mlp": exported_mlp}[head]
    predictor = ox.OnnxFlowPredictor(exported["paths"][variant], intra_op_threads=2)
    rng = np.random.default_rng(5)
    for n0, n1 in ((700, 650), (40, 900), (0, 30), (25, 0), (0, 0)):
        pts0, pts1 = _cloud(rng, n0), _cloud(rng, n1)
        pts0[np.arange(n0) % 9 == 4, 0] = np.nan
        pts1[np.arange(n1) % 11 == 2, 1] = np.inf
        flow_tf, valid_tf = _tensorflow(exported["module"], pts1, pts0)
        out = predictor(pts1, pts0, POSE_TM1, POSE_T0)
        flow, valid = out["flow_mps"], out["point_valid"]
        assert flow.shape == (n0, 3) and valid.shape == (n0,)
        np.testing.assert_array_equal(valid, valid_tf)
        assert np.isfinite(flow).all()
        np.testing.assert_array_equal(flow[~valid], 0.0)
        if n0:
            np.testing.assert_allclose(flow, flow_tf, atol=1e-4 + 4e-6 * np.abs(flow_tf).max(), rtol=0)
        if n0 > 100:
            assert 0.3 * n0 < valid.sum() < 0.95 * n0 and np.abs(flow_tf).max() > 1.0


def test_gru_head_graph_ops(exported_gru):
    loop, single = (onnx.load(exported_gru["paths"][v]) for v in ox.VARIANTS)
    assert ("", "Loop") in ox.graph_ops(loop)
    single_ops = {op for _, op in ox.graph_ops(single)}
    assert single_ops == GRU_SINGLE_CHUNK_OPS, (single_ops - GRU_SINGLE_CHUNK_OPS, GRU_SINGLE_CHUNK_OPS - single_ops)
    assert not single_ops & set(ox.CONTROL_FLOW_OPS)
    assert [i.type.tensor_type.elem_type for i in single.graph.input] == [TensorProto.FLOAT] * 3
    assert not [n for n in _all_nodes(single) if n.op_type == "Cast" and
                helper.get_attribute_value(n.attribute[0]) == TensorProto.DOUBLE]
    assert not [t for t in single.graph.initializer if t.data_type == TensorProto.DOUBLE]


def test_gru_head_paper_config_single_chunk_at_32k_points(tmp_path):
    """The paper's grid and widths with the GRU head (random weights) at 32,000 points: the single_chunk graph (no
    control flow, no float64) in onnxruntime within 1e-3 m/s of TensorFlow's serving forward, the same validity."""
    from ff3d_tf.config import load_config
    from conftest import ROOT
    cfg = load_config(f"{ROOT}/configs/fastflow3d_waymo.yaml", ["model.head=gru"])
    model = build_model(cfg)
    path = str(tmp_path / "gru.onnx")
    info = ox.export_onnx(model, path, "single_chunk")
    assert not set(info["ops"]) & set(ox.CONTROL_FLOW_OPS) and info["pose_inputs"] == "relative_float32"
    rng = np.random.default_rng(7)
    pts0, pts1 = _cloud(rng, 32000, 90.0), _cloud(rng, 32000, 90.0)  # the grid is +-85 m
    pts0[::97, 1] = np.nan
    flow_tf, valid_tf = _tensorflow(FlowServingModule(model, cfg.data.point_bucket_base, cfg.model.jit_compile),
                                    pts1, pts0)
    out = ox.OnnxFlowPredictor(path, intra_op_threads=2)(pts1, pts0, POSE_TM1, POSE_T0)
    np.testing.assert_array_equal(out["point_valid"], valid_tf)
    assert valid_tf.sum() > 20000 and np.abs(flow_tf).max() > 1.0
    np.testing.assert_allclose(out["flow_mps"], flow_tf, atol=1e-3, rtol=0)
    np.testing.assert_array_equal(out["flow_mps"][~valid_tf], 0.0)

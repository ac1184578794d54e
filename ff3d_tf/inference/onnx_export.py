"""ONNX export of the serving forward, for ONNX Runtime and TensorRT, and an ONNX Runtime predictor.

The graph is the SavedModel's serving forward (`ff3d_tf.inference.saved_model`) without its pose assertions (ONNX
has no assert; `OnnxFlowPredictor` checks the poses on the host, with the same rules):

  inputs   points_tm1 [N1,5] float32, points_t0 [N0,5] float32 (x, y, z in metres in each frame's own vehicle frame,
           intensity, elongation; N0, N1 dynamic, 0 allowed), and the ego motion, as `pose_inputs` says:
             "world_float64"    pose_tm1, pose_t0 [4,4] float64 (vehicle -> world), composed inside the graph as
                                rigid_inverse(pose_t0) @ pose_tm1 (`geometry.rigid_inverse`: ONNX has no matrix
                                inverse) and applied in float64, as the SavedModel does;
             "relative_float32" t0_from_tm1 [4,4] float32 (vehicle frame at t-1 -> at t0), composed by the caller in
                                float64 (`geometry.t0_from_tm1_np`) and applied in float32: no float64 tensor in the
                                graph (TensorRT has none).
  outputs  flow_mps [N0,3] float32 (m/s, vehicle frame at t0; 0 where invalid), point_valid [N0] bool.
A model of more sweeps (`data.num_frames`) takes every cloud in the order of its slots, the oldest slot first
(points_tm2 before points_tm1), then every pose in the same order, or one t0_from_tm{k} per past sweep
(`input_names`); for a model of Argoverse 2 challenge records (`data.partner=next`) points_tm1 is the NEXT sweep t+1
(docs/deployment.md, "Several sweeps").

Metadata (`METADATA_KEYS`): the variant and pose inputs, the order of the sweeps the model reads (`ff3d_partner`,
`ff3d_temporal`: `OnnxFlowPredictor.order`) and the config the tools load when given the file (`ff3d_config`, YAML:
`saved_config_yaml`).

Variants (`VARIANTS`):
  "loop"          the point encoder in chunks of `ops.POINT_CHUNK` points, an ONNX `Loop` per cloud: memory bounded at
                  any cloud size; for ONNX Runtime.
  "single_chunk"  the whole cloud in one chunk (`ops.ONE_CHUNK`): no `Loop`, no control flow; for TensorRT 10, which
                  runs `ScatterElements` with reduction add as a plugin. Memory grows with the cloud (the scatter's
                  indices are [N, C] int64).

What the conversion changes, each for a measured reason (tf2onnx 1.17, onnxruntime 1.31, opset 17):
  - tf.math.unsorted_segment_sum becomes ScatterElements(reduction="add") into a zero grid; ids outside
    [0, num_segments) (TensorFlow drops them; ONNX reads a negative index from the end) add a zero. tf2onnx's
    own lowering fails in onnxruntime on the model's empty first chunk (a negative shape) and needs memory
    proportional to the fullest pillar; ScatterND with reduction add races on onnxruntime's CPU with 2 threads
    (sums differ from call to call, onnxruntime issues 18048 and 23396); ScatterElements is deterministic.
  - tf.where of floats becomes ONNX Where: tf2onnx writes it as cond * x + (1 - cond) * y, which turns the masked
    NaN of a non-finite point into a NaN flow (0 * NaN = NaN).
  - opset >= 16 (`MIN_OPSET`): below, ScatterElements has no reduction and tf2onnx silently drops it.
  - the model runs in compile mode "none" (an export twin with the same weights): "hybrid"/"xla" leave XLA calls
    in the graph that do not convert.
  - each cloud is padded inside the graph to at least one masked point: an empty cloud fails at a reduction.

Every op of the written graph, its subgraphs included, is checked against the ONNX standard schemas at the opset
(`check_graph`): an op tf2onnx could not map (it logs and continues) fails the export, naming the op.
tf2onnx and onnx are imported inside the functions (onnxruntime in `OnnxFlowPredictor`): importing this module
imports neither. The two op handlers use tf2onnx's internal graph API, so they live in `ff3d_tf.internals`
(`tf2onnx_custom_op_handlers`, with the versions they were checked on).
"""
from __future__ import annotations

import collections
import json
import logging

import numpy as np
import tensorflow as tf

from ff3d_tf import geometry, internals, schema
from ff3d_tf.checkpoints import with_model_partner
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.model import ops
from ff3d_tf.model.fastflow3d import FastFlow3D
from ff3d_tf.predictor import ServingPredictor, num_frames_of, serving_names

VARIANTS = ("loop", "single_chunk")
POSE_INPUTS = ("world_float64", "relative_float32")
DEFAULT_POSE_INPUTS = {"loop": "world_float64", "single_chunk": "relative_float32"}
DEFAULT_OPSET = 17
MIN_OPSET = 16  # ScatterElements' reduction attribute
POINT_WIDTH = 5  # x, y, z, intensity, elongation
OUTPUT_NAMES = ("flow_mps", "point_valid")
CONTROL_FLOW_OPS = ("Loop", "If", "Scan")
_METADATA_KEYS = ("ff3d_variant", "ff3d_pose_inputs")  # every file of this export has them
ORDER_KEYS = {"partner": "ff3d_partner", "temporal": "ff3d_temporal"}  # the sweeps' order (`SweepOrder`)
CONFIG_KEY = "ff3d_config"  # the config of the export, YAML (`saved_config_yaml`)
METADATA_KEYS = _METADATA_KEYS + tuple(ORDER_KEYS.values()) + (CONFIG_KEY,)


def input_names(pose_inputs: str, num_frames: int = 2) -> tuple[str, ...]:
    """The graph's input names, in order, for a `POSE_INPUTS` choice: the clouds oldest first, then the poses in the
    same order (`ff3d_tf.predictor.serving_names`) or each past sweep's t0_from_tm{k}, oldest first."""
    _check_choice("pose_inputs", pose_inputs, POSE_INPUTS)
    points, poses = serving_names(num_frames)
    return points + (poses if pose_inputs == "world_float64" else tuple(f"t0_from_{c}" for c in
                                                                         schema.sweep_clouds(num_frames)[:0:-1]))


def _check_choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"{name}={value!r}: one of {', '.join(choices)}")


# -- the TensorFlow function that is converted ----------------------------------------------------------------------

def export_twin(model: FastFlow3D, variant: str) -> FastFlow3D:
    """A float32 copy of `model` in compile mode "none" (its plan's forms otherwise) with the variant's point chunk
    and the same weights."""
    _check_choice("variant", variant, VARIANTS)
    chunk = ops.ONE_CHUNK if variant == "single_chunk" else ops.POINT_CHUNK
    plan = model.plan.replace(compile_mode="none", precision="float32")
    twin = FastFlow3D.from_config({**model.get_config(), "plan": plan.to_dict(), "point_chunk_size": chunk,
                                   "dtype": "float32"})
    twin.build()
    weights = model.get_weights()
    if [w.shape for w in weights] != [tuple(v.shape) for v in twin.weights]:
        raise ValueError("export twin: the model's weights do not match its own config (a model built by hand?)")
    twin.set_weights(weights)
    return twin


def _at_least_one_point(points, n):
    """[N,5] -> ([1,max(N,1),5], mask [1,max(N,1)]): an empty cloud becomes one masked zero point (a concat and a
    slice, which every runtime has; no dynamic Pad)."""
    m = tf.maximum(n, 1)
    padded = tf.concat([points, tf.zeros([1, POINT_WIDTH], points.dtype)], 0)[:m]
    return padded[None], (tf.range(m) < n)[None]


def serving_function(model: FastFlow3D, pose_inputs: str):
    """(tf.function, input signature) of the graph that is converted; `model` should be an `export_twin`."""
    num_frames = model.num_frames
    names = input_names(pose_inputs, num_frames)

    def flow(clouds, past_xyz_in_t0):
        """clouds: [N,5] each, t0 first; past_xyz_in_t0: each past cloud's xyz in the t0 frame, t-1 first."""
        inputs = {}
        for k, cloud in enumerate(schema.sweep_clouds(num_frames)):
            points = clouds[k] if k == 0 else tf.concat([past_xyz_in_t0[k - 1], clouds[k][:, 3:]], -1)
            padded, mask = _at_least_one_point(points, tf.shape(clouds[k])[0])
            keys = schema.cloud_keys(cloud)
            inputs.update({keys["xyz"]: padded[..., :3], keys["features"]: padded[..., 3:], keys["mask"]: mask})
        out = model(inputs, training=False)
        n0 = tf.shape(clouds[0])[0]
        return {"flow_mps": out["flow_mps"][0, :n0], "point_valid": out["point_valid"][0, :n0]}

    points = [tf.TensorSpec([None, POINT_WIDTH], tf.float32, name=n) for n in names[:num_frames]]
    if pose_inputs == "world_float64":
        def fn(*args):
            clouds, poses = args[:num_frames][::-1], args[num_frames:][::-1]  # t0 first
            world_to_t0 = geometry.rigid_inverse(poses[0])
            return flow(clouds, [geometry.transform_points(c[:, :3], world_to_t0 @ pose)
                                 for c, pose in zip(clouds[1:], poses[1:])])
        signature = points + [tf.TensorSpec([4, 4], tf.float64, name=n) for n in names[num_frames:]]
    else:
        def fn(*args):
            clouds, motions = args[:num_frames][::-1], args[num_frames:][::-1]  # t0 first; t0_from_tm1 first
            return flow(clouds, [tf.matmul(c[:, :3], m[:3, :3], transpose_b=True) + m[:3, 3]
                                 for c, m in zip(clouds[1:], motions)])
        signature = points + [tf.TensorSpec([4, 4], tf.float32, name=n) for n in names[num_frames:]]
    return tf.function(fn, autograph=False), signature  # no Python control flow on tensors to convert


# -- export and checks ----------------------------------------------------------------------------------------------

class _Errors(logging.Handler):
    """Collects tf2onnx's ERROR records: `from_function` converts with continue_on_error and only logs failures."""

    def __init__(self):
        super().__init__(logging.ERROR)
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def _check_opset(opset: int) -> None:
    if opset < MIN_OPSET:
        raise ValueError(f"opset={opset}: needs >= {MIN_OPSET} (below, ScatterElements has no reduction and tf2onnx "
                         f"would drop the pillar sums' reduction)")


def convert_function(fn, input_signature, opset: int = DEFAULT_OPSET):
    """A tf.function as an ONNX ModelProto with the project's op handlers (`internals.tf2onnx_custom_op_handlers`:
    unsorted_segment_sum as ScatterElements(add), selects as Where); raises RuntimeError
    naming what tf2onnx failed to convert (it logs failures and carries on)."""
    import tf2onnx
    _check_opset(opset)
    errors, tf2onnx_logger = _Errors(), logging.getLogger("tf2onnx")
    tf2onnx_logger.addHandler(errors)
    try:
        proto, _ = tf2onnx.convert.from_function(fn, input_signature=input_signature, opset=opset,
                                                 custom_op_handlers=internals.tf2onnx_custom_op_handlers())
    finally:
        tf2onnx_logger.removeHandler(errors)
    if errors.messages:
        raise RuntimeError("tf2onnx failed to convert the graph: " + " | ".join(errors.messages[:5]))
    return proto


def convert(model: FastFlow3D, variant: str = "loop", pose_inputs: str | None = None, opset: int = DEFAULT_OPSET,
            config_yaml: str | None = None):
    """The ONNX ModelProto of `model`'s serving forward (see the module docstring), checked (`check_graph`), with the
    metadata of `METADATA_KEYS` (`config_yaml`: the config's, when given)."""
    import onnx
    _check_choice("variant", variant, VARIANTS)
    pose_inputs = DEFAULT_POSE_INPUTS[variant] if pose_inputs is None else pose_inputs
    _check_choice("pose_inputs", pose_inputs, POSE_INPUTS)
    _check_opset(opset)  # before the twin is built and traced
    proto = convert_function(*serving_function(export_twin(model, variant), pose_inputs), opset)
    props = {**dict(zip(_METADATA_KEYS, (variant, pose_inputs))), ORDER_KEYS["partner"]: model.partner,
             ORDER_KEYS["temporal"]: model.temporal}
    onnx.helper.set_model_props(proto, {**props, **({CONFIG_KEY: config_yaml} if config_yaml else {})})
    check_graph(proto, variant, pose_inputs)
    return proto


def export_onnx(model: FastFlow3D, path: str, variant: str = "loop", pose_inputs: str | None = None,
                opset: int = DEFAULT_OPSET, cfg: ExperimentConfig | None = None) -> dict:
    """Writes `model`'s serving forward as an ONNX file at `path`, with the config it was restored with (`cfg`, its
    partner the model's) in its metadata when given; returns {variant, pose_inputs, opset, inputs, outputs, ops}
    (ops: `graph_ops` as "op": count)."""
    import onnx
    import yaml
    config_yaml = None
    if cfg is not None:
        tree = json.loads(json.dumps(with_model_partner(cfg, model).to_dict()))
        config_yaml = yaml.safe_dump(tree, sort_keys=False)
    proto = convert(model, variant, pose_inputs, opset, config_yaml)
    onnx.save(proto, path)
    meta = {p.key: p.value for p in proto.metadata_props}
    return {"path": path, "variant": variant, "pose_inputs": meta["ff3d_pose_inputs"], "opset": opset,
            "inputs": [i.name for i in proto.graph.input], "outputs": [o.name for o in proto.graph.output],
            "ops": {op: n for (_, op), n in sorted(graph_ops(proto).items())}}


def _graphs(graph):
    """`graph` and every subgraph of its nodes (Loop bodies, If branches), depth first."""
    yield graph
    for node in graph.node:
        for attr in node.attribute:
            for sub in ([attr.g] if attr.HasField("g") else []) + list(attr.graphs):
                yield from _graphs(sub)


def graph_ops(proto) -> collections.Counter:
    """{(domain, op type): count} over the graph and its subgraphs."""
    return collections.Counter((n.domain, n.op_type) for g in _graphs(proto.graph) for n in g.node)


def check_graph(proto, variant: str, pose_inputs: str) -> None:
    """Raises ValueError unless every op is a standard ONNX op at the model's opset, no ScatterND reduces (it races
    on onnxruntime's CPU), the graph has the expected inputs and outputs, and, for "single_chunk", there is no
    control flow; with "relative_float32" poses, no float64 tensor enters or is made."""
    import onnx
    opset = {o.domain: o.version for o in proto.opset_import}.get("", 0)
    problems = []
    for g in _graphs(proto.graph):
        for n in g.node:
            if n.domain not in ("", "ai.onnx"):
                problems.append(f"{n.op_type} of domain {n.domain!r} (node {n.name})")
            elif not onnx.defs.has(n.op_type):
                problems.append(f"{n.op_type} is no ONNX op (node {n.name}: tf2onnx left it unconverted)")
            elif onnx.defs.get_schema(n.op_type, opset).since_version > opset:
                problems.append(f"{n.op_type} needs a newer opset than {opset}")
            attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
            if n.op_type == "ScatterND" and attrs.get("reduction", b"none") not in (b"none", "none"):
                problems.append(f"ScatterND with reduction {attrs['reduction']!r} (node {n.name}: races on CPU)")
            if n.op_type in CONTROL_FLOW_OPS and variant == "single_chunk":
                problems.append(f"{n.op_type} in the single_chunk graph (node {n.name})")
            if pose_inputs == "relative_float32" and n.op_type == "Cast" and \
                    attrs.get("to") == onnx.TensorProto.DOUBLE:
                problems.append(f"a float64 Cast (node {n.name}) with relative_float32 poses")
        if pose_inputs == "relative_float32":
            problems += [f"float64 initializer {t.name}" for t in g.initializer
                         if t.data_type == onnx.TensorProto.DOUBLE]
    names = [i.name for i in proto.graph.input]
    expected = list(input_names(pose_inputs, max(2, num_frames_of(names))))
    if names != expected:
        problems.append(f"inputs {names}, expected {expected}")
    if [o.name for o in proto.graph.output] != list(OUTPUT_NAMES):
        problems.append(f"outputs {[o.name for o in proto.graph.output]}, expected {list(OUTPUT_NAMES)}")
    if problems:
        raise ValueError(f"ONNX graph ({variant}) is not portable: " + "; ".join(problems))


def saved_config_yaml(path: str) -> str | None:
    """The config saved in the metadata of the ONNX file at `path` (YAML), None when it has none."""
    import onnx
    try:
        proto = onnx.load(path, load_external_data=False)
    except Exception as err:  # noqa: BLE001  (onnx raises protobuf's DecodeError, OSError, ...)
        raise ValueError(f"{path}: not a readable ONNX file ({type(err).__name__})") from None
    return {p.key: p.value for p in proto.metadata_props}.get(CONFIG_KEY)


# -- running it with onnxruntime ------------------------------------------------------------------------------------

class OnnxFlowPredictor(ServingPredictor):
    """An exported ONNX file under onnxruntime (CPU): `predictor(points_tm1, points_t0, pose_tm1, pose_t0)` (a model of
    more sweeps: every cloud oldest first, then every pose, `ff3d_tf.predictor.serving_names`) ->
    {"flow_mps" [N0,3], "point_valid" [N0]} as NumPy, whatever the file's `pose_inputs`; a
    `ff3d_tf.predictor.Predictor` too (`predict(batch, example)` calls it with the pair's raw clouds).

    Checks first, with a `ValueError` naming the argument: clouds float32 [N,5], poses float64 [4,4] and rigid
    (`geometry.pose_problem_np`, the SavedModel's rules). `intra_op_threads`: onnxruntime's intra-op threads (the
    outputs do not depend on it: the pillar sums are ScatterElements, deterministic).
    """

    def __init__(self, path: str, intra_op_threads: int = 2):
        import onnxruntime as ort
        options = ort.SessionOptions()
        options.intra_op_num_threads = int(intra_op_threads)
        options.inter_op_num_threads = 1
        self.path = path
        self.session = ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])
        meta = self.session.get_modelmeta().custom_metadata_map
        missing = [k for k in _METADATA_KEYS if k not in meta]
        if missing:
            raise ValueError(f"{path}: not written by ff3d_tf's ONNX export (metadata {missing} missing)")
        self.variant, self.pose_inputs = meta["ff3d_variant"], meta["ff3d_pose_inputs"]
        _check_choice(f"{path}: pose_inputs", self.pose_inputs, POSE_INPUTS)
        self.num_frames = num_frames_of([i.name for i in self.session.get_inputs()])
        # The order of the sweeps the model reads as the file records it (`ff3d_tf.inference.predictor.sweep_order`)
        self.recorded_order = {k: meta[key] for k, key in ORDER_KEYS.items() if key in meta}

    def feeds(self, *clouds_and_poses, **by_name) -> dict:
        """The session's inputs for one example (clouds oldest first, then their poses; or by name), after the
        checks."""
        point_names, pose_names = serving_names(self.num_frames)
        values = self.arguments(self.path, self.num_frames, clouds_and_poses, by_name)
        for name, value in values.items():
            dtype, shape = (np.float32, (None, POINT_WIDTH)) if name.startswith("points") else (np.float64, (4, 4))
            a = np.asarray(value)
            if a.dtype != dtype or a.ndim != 2 or any(w is not None and w != g for w, g in zip(shape, a.shape)):
                want = ", ".join("N" if d is None else str(d) for d in shape)
                raise ValueError(f"{self.path}: input {name} must be {np.dtype(dtype).name} [{want}], got "
                                 f"{a.dtype.name} {list(a.shape)}")
            values[name] = a
        for name in pose_names:
            problem = geometry.pose_problem_np(values[name], name)
            if problem:
                raise ValueError(f"{self.path}: {problem}")
        if self.pose_inputs == "world_float64":
            return values
        motions = {f"t0_from_{name[len('pose_'):]}": geometry.t0_from_tm1_np(values["pose_t0"], values[name])
                   .astype(np.float32) for name in pose_names[:-1]}
        return {**{n: values[n] for n in point_names}, **motions}

    def __call__(self, *clouds_and_poses, **by_name) -> dict:
        flow, valid = self.session.run(list(OUTPUT_NAMES), self.feeds(*clouds_and_poses, **by_name))
        return {"flow_mps": flow, "point_valid": valid}

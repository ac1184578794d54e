"""A model of three sweeps (`model.temporal=delta`) through every serving runtime: the SavedModel signature, both ONNX
variants under onnxruntime and the portable XLA export each give the Keras model's flow for raw clouds in their own
frames and their poses; a pose that is not rigid is refused by name; an export of another number of sweeps than the
config's is refused before any example is read."""
import numpy as np
import pytest

from ff3d_tf import geometry, schema
from ff3d_tf.config import ConfigError, replace_config
from ff3d_tf.inference import onnx_export, saved_model
from ff3d_tf.inference.predictor import load_predictor
from ff3d_tf.model.fastflow3d import build_model
from ff3d_tf.predictor import serving_clouds, serving_names


def _pose(yaw, x, y=0.0):
    c, s = np.cos(yaw), np.sin(yaw)
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:2, 3] = x, y
    return pose


POSES = (_pose(0.30, 1000.0, -500.0), _pose(0.32, 1001.0, -499.6), _pose(0.35, 1002.1, -499.1))  # t-2, t-1, t0


@pytest.fixture(scope="module")
def sequence_model(tiny_config):
    cfg = replace_config(tiny_config, {"data.num_frames": 3, "model.temporal": "delta"})
    return cfg, build_model(cfg, compile_mode="none")


def _clouds(seed=0):
    """Three clouds (t-2, t-1, t0), each [N,5] in its own vehicle frame."""
    rng = np.random.default_rng(seed)
    return [np.concatenate([rng.uniform([-35, -35, -1], [35, 35, 2], (n, 3)), rng.uniform(0, 1, (n, 2))],
                           1).astype(np.float32) for n in (260, 300, 280)]


def _keras_flow(model, clouds):
    """The Keras model on the clouds moved into the t0 frame by NumPy (the reference)."""
    inputs = {}
    for k, cloud in enumerate(schema.sweep_clouds(3)):
        points, keys = clouds[2 - k], schema.cloud_keys(cloud)
        xyz = points[:, :3] if k == 0 else geometry.transform_points_np(
            points[:, :3], geometry.t0_from_tm1_np(POSES[2], POSES[2 - k])).astype(np.float32)
        inputs.update({keys["xyz"]: xyz[None], keys["features"]: points[None, :, 3:],
                       keys["mask"]: np.ones((1, len(points)), bool)})
    return model(inputs)["flow_mps"][0].numpy()


def test_serving_names_and_clouds_of_an_example():
    assert serving_names(2) == (("points_tm1", "points_t0"), ("pose_tm1", "pose_t0"))
    assert serving_names(3) == (("points_tm2", "points_tm1", "points_t0"), ("pose_tm2", "pose_tm1", "pose_t0"))
    clouds = _clouds(1)
    example = {"pose_t0": POSES[2], "pose_tm1": POSES[1], "pose_tm2": POSES[0],
               "points_xyz_t0": clouds[2][:, :3], "point_features_t0": clouds[2][:, 3:]}
    for k, cloud in ((1, "tm1"), (2, "tm2")):
        keys = schema.cloud_keys(cloud)
        example[keys["xyz"]] = geometry.transform_points_np(
            clouds[2 - k][:, :3], geometry.t0_from_tm1_np(POSES[2], POSES[2 - k])).astype(np.float32)
        example[keys["features"]] = clouds[2 - k][:, 3:]
    args = serving_clouds(example)
    assert len(args) == 6
    for got, want in zip(args[:3], clouds):  # back in each sweep's own frame
        np.testing.assert_allclose(got, want, atol=1e-3)
    for got, want in zip(args[3:], POSES):
        np.testing.assert_array_equal(got, want)


def test_saved_model_takes_three_clouds_and_refuses_a_bad_pose(sequence_model, tmp_path):
    cfg, model = sequence_model
    path = saved_model.export_saved_model(model, str(tmp_path / "sm"), cfg.data.point_bucket_base, jit_compile=False)
    predictor = saved_model.SavedModelPredictor(path)
    assert predictor.num_frames == 3
    clouds = _clouds()
    ref = _keras_flow(model, clouds)
    np.testing.assert_allclose(predictor(*clouds, *POSES)["flow_mps"].numpy(), ref, atol=1e-4)
    sheared = POSES[0].copy()
    sheared[0, 1] += 0.1
    with pytest.raises(ValueError, match="pose_tm2"):
        predictor(*clouds, sheared, *POSES[1:])
    with pytest.raises(ValueError, match="takes 6 arguments.*missing"):
        predictor(clouds[1], clouds[2], *POSES[1:])


@pytest.mark.parametrize("variant", onnx_export.VARIANTS)
def test_onnx_takes_three_clouds(sequence_model, tmp_path, variant):
    _, model = sequence_model
    path = str(tmp_path / f"{variant}.onnx")
    onnx_export.export_onnx(model, path, variant)
    predictor = onnx_export.OnnxFlowPredictor(path)
    names = [i.name for i in predictor.session.get_inputs()]
    assert names == list(onnx_export.input_names(predictor.pose_inputs, 3))
    clouds = _clouds(2)
    np.testing.assert_allclose(predictor(*clouds, *POSES)["flow_mps"], _keras_flow(model, clouds), atol=1e-4)


def test_an_export_of_other_sweeps_is_refused_before_work(sequence_model, tiny_config, tmp_path):
    cfg, model = sequence_model
    path = saved_model.export_saved_model(model, str(tmp_path / "sm"), cfg.data.point_bucket_base, jit_compile=False)
    assert load_predictor(cfg, path).num_frames == 3
    with pytest.raises(ConfigError, match="reads 3 sweeps.*data.num_frames=2"):
        load_predictor(tiny_config, path)


def test_xla_export_of_three_sweeps_equals_tensorflow(sequence_model, tmp_path):
    pytest.importorskip("jax", reason="the xla extra (pip install .[xla]) provides jax")
    from ff3d_tf.inference.xla_artifact import XlaPredictor
    from ff3d_tf.inference.xla_export import export_forward
    cfg, model = sequence_model
    manifest = export_forward(cfg, model, (900,), str(tmp_path / "xla"), log=lambda _: None)
    assert manifest["input_keys"] == list(schema.model_input_keys(3))
    predictor = XlaPredictor(str(tmp_path / "xla"))
    assert predictor.num_frames == 3
    clouds = _clouds(3)
    ref = _keras_flow(model, clouds)
    batch = {}
    for k, cloud in enumerate(schema.sweep_clouds(3)):
        keys, points = schema.cloud_keys(cloud), clouds[2 - k]
        xyz = points[:, :3] if k == 0 else geometry.transform_points_np(
            points[:, :3], geometry.t0_from_tm1_np(POSES[2], POSES[2 - k])).astype(np.float32)
        batch.update({keys["xyz"]: xyz[None], keys["features"]: points[None, :, 3:],
                      keys["mask"]: np.ones((1, len(points)), bool)})
    flow, _ = predictor.predict(batch, {"num_points_t0": len(clouds[2])})
    np.testing.assert_allclose(flow, ref, atol=1e-4)


@pytest.mark.slow  # three exports of a model: ~80 s (make test-docs-commands runs it)
def test_a_model_of_the_next_sweep_records_its_order_in_every_export(tiny_config, tmp_path):
    """A model of Argoverse 2 challenge records (data.partner=next: t+1 in its t-1 slot) keeps that order in the
    SavedModel (its module, without any config beside it), the ONNX file (its metadata, with the config) and the
    portable XLA export (manifest.json); each is refused for examples of the previous sweep, naming both orders,
    and serves the clouds in its slots' order (points_tm2 = t-1, points_tm1 = t+1, points_t0)."""
    pytest.importorskip("jax", reason="the xla extra (pip install .[xla]) provides jax")
    import yaml
    from ff3d_tf.inference.predictor import SweepOrder, sweep_order
    from ff3d_tf.inference.xla_export import export_forward
    cfg = replace_config(tiny_config, {"data.num_frames": 3, "model.temporal": "delta",
                                       "data.source": "pair_records", "data.partner": "next"})
    model = build_model(cfg, compile_mode="none")
    assert model.partner == "next"
    paths = {"saved_model": saved_model.export_saved_model(model, str(tmp_path / "sm"), cfg.data.point_bucket_base,
                                                           jit_compile=False),
             "onnx": str(tmp_path / "m.onnx"), "xla": str(tmp_path / "xla")}
    onnx_export.export_onnx(model, paths["onnx"], "single_chunk", cfg=replace_config(cfg, {"data.partner": None}))
    export_forward(cfg, model, (900,), paths["xla"], log=lambda _: None)
    assert yaml.safe_load(onnx_export.saved_config_yaml(paths["onnx"]))["data"]["partner"] == "next"
    previous = replace_config(cfg, {"data.partner": "previous"})
    clouds = _clouds(4)  # in slot order, oldest slot first: t-1 (tm2), t+1 (tm1), t0
    ref = _keras_flow(model, clouds)
    for kind, path in paths.items():
        predictor = load_predictor(cfg, path)
        assert sweep_order(predictor) == SweepOrder(3, "next", "delta"), kind
        with pytest.raises(ConfigError, match="trained with the next sweep .*these examples hold the previous"):
            load_predictor(previous, path)
        if kind != "xla":
            np.testing.assert_allclose(np.asarray(predictor(*clouds, *POSES)["flow_mps"]), ref, atol=1e-4)


def _sequence(num_frames: int, seed: int):
    """`num_frames` clouds, oldest first, each [N,5] in its own vehicle frame, and their poses (a car driving ~1 m per
    sweep while turning)."""
    rng = np.random.default_rng(seed)
    clouds = [np.concatenate([rng.uniform([-35, -35, -1], [35, 35, 2], (n, 3)), rng.uniform(0, 1, (n, 2))],
                             1).astype(np.float32) for n in rng.integers(240, 320, num_frames)]
    poses = [_pose(0.3 + 0.02 * k, 1000.0 + 1.05 * k, -500.0 + 0.4 * k) for k in range(num_frames)]
    return clouds, poses


def _model_batch(clouds, poses):
    """The model's inputs (slot order: t0, tm1, ...) for clouds and poses given oldest first: every cloud moved into
    the t0 frame by NumPy."""
    n, batch = len(clouds), {}
    for k, cloud in enumerate(schema.sweep_clouds(n)):
        points, keys = clouds[n - 1 - k], schema.cloud_keys(cloud)
        xyz = points[:, :3] if k == 0 else geometry.transform_points_np(
            points[:, :3], geometry.t0_from_tm1_np(poses[-1], poses[n - 1 - k])).astype(np.float32)
        batch.update({keys["xyz"]: xyz[None], keys["features"]: points[None, :, 3:],
                      keys["mask"]: np.ones((1, len(points)), bool)})
    return batch


@pytest.mark.slow  # four exports of each of four models: minutes
@pytest.mark.parametrize("temporal,num_frames", [("delta", 3), ("delta", 5), ("stack", 3), ("stack", 5)])
def test_every_export_of_the_recipes_head_equals_tensorflow(tiny_config, tmp_path, temporal, num_frames):
    """The multi-sweep recipes' model (DeltaFlow's point head, its BatchNorm statistics set away from the identity so
    that a runtime that dropped them would differ) through the SavedModel, both ONNX variants and the portable XLA
    export: each gives the Keras model's flow, to float32 rounding."""
    pytest.importorskip("jax", reason="the xla extra (pip install .[xla]) provides jax")
    from ff3d_tf.inference.xla_artifact import XlaPredictor
    from ff3d_tf.inference.xla_export import export_forward
    cfg = replace_config(tiny_config, {"data.num_frames": num_frames, "model.temporal": temporal,
                                       "model.head": "mlp"})
    model = build_model(cfg, compile_mode="none")
    model.head_mlp.norm.moving_mean.assign(np.linspace(-0.3, 0.3, model.head_mlp.units).astype(np.float32))
    model.head_mlp.norm.moving_variance.assign(np.linspace(0.5, 2.0, model.head_mlp.units).astype(np.float32))
    clouds, poses = _sequence(num_frames, seed=num_frames)
    batch = _model_batch(clouds, poses)
    ref = model(batch)["flow_mps"][0].numpy()
    got = {}
    sm = saved_model.SavedModelPredictor(saved_model.export_saved_model(
        model, str(tmp_path / "sm"), cfg.data.point_bucket_base, jit_compile=False))
    got["saved_model"] = sm(*clouds, *poses)["flow_mps"].numpy()
    for variant in onnx_export.VARIANTS:
        path = str(tmp_path / f"{variant}.onnx")
        onnx_export.export_onnx(model, path, variant)
        got[variant] = onnx_export.OnnxFlowPredictor(path)(*clouds, *poses)["flow_mps"]
    export_forward(cfg, model, (2048,), str(tmp_path / "xla"), log=lambda _: None)
    got["xla"] = XlaPredictor(str(tmp_path / "xla")).predict(batch, {"num_points_t0": len(clouds[-1])})[0]
    assert np.abs(ref).max() > 1e-3  # a flow to compare, not zeros
    for kind, flow in got.items():
        np.testing.assert_allclose(np.asarray(flow), ref, atol=1e-4, err_msg=kind)

"""Precision (`model.mixed_precision` = false | true | auto): the CPU flag detection, its resolution and log line, and
what a bfloat16 model computes in which dtype (convolutions bfloat16; variables, coordinates, pillar indices, pillar
sums and the head float32), against a float32 model with the same weights."""
import collections
import logging

import keras
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf import cpu
from ff3d_tf.config import ConfigError, load_config, replace_config
from ff3d_tf.model import build_model
from ff3d_tf.model import compile as compile_lib

# Flags lines (shortened) of a CPU with AMX, one with AVX-512 BF16 alone, one with neither.
_FLAGS_AMX = "flags\t\t: fpu sse sse2 avx2 avx512f avx512bw avx512_bf16 avx512_vnni amx_bf16 amx_tile amx_int8\n"
_FLAGS_AVX512_BF16 = "flags\t\t: fpu sse sse2 avx2 avx512f avx512bw avx512_bf16 avx512_vnni\n"
_FLAGS_PLAIN = "flags\t\t: fpu sse sse2 avx2 avx512f avx512bw avx512_vnni\n"
AMD, INTEL = "AuthenticAMD", "GenuineIntel"


def _cpuinfo(vendor, *flag_lines):
    """/proc/cpuinfo's layout: one block per processor, "key<TAB>: value" lines, a blank line between blocks."""
    return "".join(f"processor\t: {i}\nvendor_id\t: {vendor}\nmodel name\t: Test CPU\n{line}"
                   "bugs\t\t: sysret_ss_attrs\n\n" for i, line in enumerate(flag_lines))


@pytest.fixture(autouse=True)
def _no_isa_cap(monkeypatch):
    """These tests describe CPUs by their cpuinfo text: a cap on this machine's oneDNN (an emulated CPU) must not
    change what they resolve to."""
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)


def test_onednn_isa_cap_removes_the_flags_it_keeps_oneDNN_from_using(monkeypatch):
    amx = _cpuinfo(INTEL, _FLAGS_AMX)
    for cap, expected in (("AVX2", ()), ("AVX512_CORE_VNNI", ()), ("AVX512_CORE_BF16", ("avx512_bf16",)),
                          ("AVX10_1_512_AMX", ("avx512_bf16", "amx_bf16")), ("ALL", ("avx512_bf16", "amx_bf16"))):
        monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", cap)
        assert compile_lib.cpu_bf16_support(amx) == (INTEL, expected), cap


def test_cpu_flag_detection_from_cpuinfo_text(tmp_path, monkeypatch):
    support = compile_lib.cpu_bf16_support
    assert support(_cpuinfo(INTEL, _FLAGS_AMX, _FLAGS_AMX)) == (INTEL, ("avx512_bf16", "amx_bf16"))
    assert support(_cpuinfo(AMD, _FLAGS_AVX512_BF16, _FLAGS_AVX512_BF16)) == (AMD, ("avx512_bf16",))
    assert support(_cpuinfo(AMD, _FLAGS_PLAIN)) == (AMD, ())
    # Only flags every processor has count (a scheduler may put the process on any of them).
    assert support(_cpuinfo(INTEL, _FLAGS_AMX, _FLAGS_AVX512_BF16)) == (INTEL, ("avx512_bf16",))
    assert support(_cpuinfo(INTEL, _FLAGS_AMX, _FLAGS_PLAIN)) == (INTEL, ())
    # A flag's name inside another word is not the flag ("avx512_bf16x" is not "avx512_bf16").
    assert support("flags : avx512_bf16x amx_bf16_not\n") == ("", ())
    assert support("processor : 0\nFeatures : fp asimd bf16\n") == ("", ())  # arm64: no flags line
    assert support("") == ("", ())
    path = tmp_path / "cpuinfo"
    path.write_text(_cpuinfo(AMD, _FLAGS_AVX512_BF16))
    monkeypatch.setattr(cpu, "CPUINFO_PATH", str(path))
    assert support() == (AMD, ("avx512_bf16",))
    monkeypatch.setattr(cpu, "CPUINFO_PATH", str(tmp_path / "missing"))
    assert support() == ("", ())  # unreadable (not Linux): no flags


def test_resolution_of_each_setting():
    amd, amx, intel = (AMD, ("avx512_bf16",)), (INTEL, ("avx512_bf16", "amx_bf16")), (INTEL, ("avx512_bf16",))
    assert compile_lib.resolve_precision("auto", "hybrid", "CPU", amd) == ("bfloat16", "AMD CPU has avx512_bf16")
    assert compile_lib.resolve_precision("auto", "none", "CPU", amx) == ("bfloat16", "CPU has amx_bf16")
    # Intel's avx512_bf16 without AMX: oneDNN's bfloat16 convolutions are slower than float32 there (measured).
    precision, reason = compile_lib.resolve_precision("auto", "hybrid", "CPU", intel)
    assert precision == "float32" and reason.startswith("GenuineIntel CPU has avx512_bf16 but no amx_bf16")
    precision, reason = compile_lib.resolve_precision("auto", "hybrid", "CPU", (AMD, ()))
    assert precision == "float32" and reason == "CPU has none of avx512_bf16, amx_bf16"
    precision, reason = compile_lib.resolve_precision("auto", "xla", "CPU", amd)
    assert precision == "float32" and "model.compile=xla" in reason
    assert compile_lib.resolve_precision("auto", "xla", "GPU", amx)[0] == "float32"
    assert compile_lib.resolve_precision("auto", "hybrid", "TPU", amx)[0] == "float32"
    # Explicit settings win over the device and the flags.
    assert compile_lib.resolve_precision(True, "xla", "GPU", ("", ())) == ("bfloat16", "as set")
    assert compile_lib.resolve_precision(False, "hybrid", "CPU", amd) == ("float32", "as set")
    with pytest.raises(ValueError, match="resolve 'auto'"):
        compile_lib.resolve_precision("auto", "auto", "CPU", amd)
    with pytest.raises(ValueError, match="true, false or auto"):
        compile_lib.resolve_precision("bf16", "hybrid", "CPU", amd)


def test_config_accepts_true_false_auto(tiny_config):
    assert load_config(None, ["model.mixed_precision=auto"]).model.mixed_precision == "auto"
    assert load_config(None, ["model.mixed_precision=true"]).model.mixed_precision is True
    assert replace_config(tiny_config, {"model.mixed_precision": False}).model.mixed_precision is False
    for bad in ("bfloat16", "1", "[true]"):
        with pytest.raises(ConfigError, match="model.mixed_precision=.*: must be one of true, false, auto"):
            load_config(None, [f"model.mixed_precision={bad}"])


def _with_cpuinfo(monkeypatch, tmp_path, vendor, flag_line):
    path = tmp_path / "cpuinfo"
    path.write_text(_cpuinfo(vendor, flag_line, flag_line))
    monkeypatch.setattr(cpu, "CPUINFO_PATH", str(path))


def test_build_model_resolves_auto_and_logs_it(tiny_config, tmp_path, monkeypatch, caplog):
    assert tiny_config.model.mixed_precision is False  # the default: float32
    cfg = replace_config(tiny_config, {"model.mixed_precision": "auto"})
    logger = "ff3d_tf.model.fastflow3d"

    def built(vendor, flags, *args):
        _with_cpuinfo(monkeypatch, tmp_path, vendor, flags)
        caplog.clear()
        with caplog.at_level(logging.INFO, logger=logger):
            return build_model(*args)
    model = built(AMD, _FLAGS_AVX512_BF16, cfg)  # tests run on CPU: auto -> hybrid for inference
    assert model.compile_mode == "hybrid" and model.conv_dtype == "bfloat16"
    assert "model.compile=auto -> hybrid for inference (" in caplog.text
    assert "model.mixed_precision=auto -> bfloat16 (AMD CPU has avx512_bf16;" in caplog.text
    assert built(INTEL, _FLAGS_AMX, cfg, "none").conv_dtype == "bfloat16"
    assert "model.mixed_precision=auto -> bfloat16 (CPU has amx_bf16;" in caplog.text
    assert built(AMD, _FLAGS_AVX512_BF16, cfg, "xla").conv_dtype == "float32"
    assert "model.mixed_precision=auto -> float32 (model.compile=xla:" in caplog.text
    assert built(INTEL, _FLAGS_AVX512_BF16, cfg).conv_dtype == "float32"
    assert "model.mixed_precision=auto -> float32 (GenuineIntel CPU has avx512_bf16 but no amx_bf16" in caplog.text
    assert built(AMD, _FLAGS_PLAIN, cfg).conv_dtype == "float32"
    assert "model.mixed_precision=auto -> float32 (CPU has none of avx512_bf16, amx_bf16;" in caplog.text
    # Explicit: the flags do not matter, but bfloat16 never meets oneDNN without its bfloat16 convolutions.
    explicit = replace_config(cfg, {"model.mixed_precision": True})
    monkeypatch.setattr("ff3d_tf.internals.onednn_enabled", lambda: True)
    with pytest.raises(ValueError, match="TF_ENABLE_ONEDNN_OPTS=0"):
        built(AMD, _FLAGS_PLAIN, explicit)
    monkeypatch.setattr("ff3d_tf.internals.onednn_enabled", lambda: False)
    assert built(AMD, _FLAGS_PLAIN, explicit).conv_dtype == "bfloat16"
    assert "model.mixed_precision=true -> bfloat16 (as set;" in caplog.text
    assert built(AMD, _FLAGS_AMX, tiny_config).conv_dtype == "float32"
    assert "model.mixed_precision=false -> float32 (as set; everything in float32)" in caplog.text
    assert "model.mixed_precision=auto would run bfloat16 here (CPU has amx_bf16)" in caplog.text  # the hint
    caplog.clear()
    built(INTEL, _FLAGS_AVX512_BF16, tiny_config)  # auto would keep float32: no hint
    assert "as set; everything in float32" in caplog.text and "would run bfloat16" not in caplog.text
    assert keras.config.dtype_policy().name == "float32"  # the global policy is restored


def _inputs(seed=3, n=400):
    """One pair on the tiny grid (32 x 32 pillars of 2.5 m over [-40, 40] m); some t0 points 0.01 m below a pillar
    boundary, where bfloat16 coordinates (8-bit mantissa: steps of 0.25 m at 32-64 m) would round into the next
    pillar."""
    rng = np.random.default_rng(seed)

    def cloud():
        xyz = rng.uniform(-38, 38, (1, n, 3)).astype(np.float32)
        xyz[..., 2] = rng.uniform(-2.5, 2.5, (1, n))
        return xyz, rng.uniform(0, 1, (1, n, 2)).astype(np.float32)
    p0, f0 = cloud()
    p0[0, :20, 0] = 37.49  # pillar column 31 starts at 37.5; bfloat16(37.49) = 37.5
    p0[0, 20:40, 1] = -32.51  # pillar row 3 starts at -32.5; bfloat16(-32.51) = -32.5
    p1, f1 = cloud()
    mask = np.ones((1, n), bool)
    mask[:, -30:] = False
    return {"points_xyz_t0": tf.constant(p0), "point_features_t0": tf.constant(f0), "point_mask_t0": tf.constant(mask),
            "points_xyz_tm1_in_t0": tf.constant(p1), "point_features_tm1": tf.constant(f1),
            "point_mask_tm1": tf.ones([1, n], tf.bool)}


@pytest.fixture(scope="module")
def models(tiny_config):
    """(float32 model, bfloat16 model) in mode hybrid with the same weights; row Z scaled for flows of ~1 m/s."""
    keras.utils.set_random_seed(4)
    m32 = build_model(replace_config(tiny_config, {"model.mixed_precision": False}), "hybrid", point_chunk_size=128)
    m16 = build_model(replace_config(tiny_config, {"model.mixed_precision": True}), "hybrid", point_chunk_size=128)
    m32.head_z.kernel.assign(m32.head_z.kernel * 0.1)
    m16.set_weights(m32.get_weights())
    return m32, m16


def _ops_by_type(graph_def, op_type):
    """(function name or "", node) of every node of `op_type` in the graph and in its function library."""
    found = [("", n) for n in graph_def.node if n.op == op_type]
    for f in graph_def.library.function:
        found += [(f.signature.name, n) for n in f.node_def if n.op == op_type]
    return found


def test_bfloat16_convolutions_float32_points_in_the_graph(models):
    """The traced hybrid forward: every convolution of rows C-U (and its fused BatchNorm) is a bfloat16 graph kernel
    outside XLA, and row V composed with the head's grid part a float32 one; every segment sum (pillar sums), floor
    (pillar indices) and gather (ungrid) is float32, inside the point stages' XLA functions; every variable is
    float32."""
    _, m16 = models
    graph_def = tf.function(lambda x: m16(x)).get_concrete_function(_inputs()).graph.as_graph_def()
    convs = _ops_by_type(graph_def, "Conv2D")
    assert all(fn == "" for fn, _ in convs)
    dtypes = collections.Counter(tf.as_dtype(node.attr["T"].type).name for _, node in convs)
    # C-R and the two 3x3 convolutions of each Upsample-Skip in bfloat16 (S's and T's U6 with the next block's U1,
    # `UpsampleSkip.into_next`; the other 1x1 ones, S's U1 and every U3, are matrix products, `layers.Conv2D`); V
    # with the head's grid part in float32 (`FastFlow3D.grid_stages`).
    assert dtypes == {"bfloat16": sum(len(s) for s in m16.encoder_stages) + 2 * 3, "float32": 1}, dtypes
    one_by_one = [n for fn, n in _ops_by_type(graph_def, "MatMul")
                  if fn == "" and ("/U1" in n.name or "/U3" in n.name)]
    assert len(one_by_one) == 1 + 3 and all(n.attr["T"].type == tf.bfloat16.as_datatype_enum for n in one_by_one)
    norms = _ops_by_type(graph_def, "FusedBatchNormV3")
    assert norms and all(n.attr["T"].type == tf.bfloat16.as_datatype_enum and
                         n.attr["U"].type == tf.float32.as_datatype_enum for _, n in norms)
    for op_type in ("UnsortedSegmentSum", "Floor"):  # pillar sums, pillar indices: in the point stages, float32
        nodes = _ops_by_type(graph_def, op_type)
        assert nodes and all(fn and n.attr["T"].type == tf.float32.as_datatype_enum for fn, n in nodes), op_type
    # The point stages' functions (their XLA programs, loops and gradients) hold no bfloat16 arithmetic: at most the
    # casts at their boundary with the convolutions and the identities that return them (the grid handed to the
    # head is the float32 output of V composed with the head's grid part).
    bf16 = tf.bfloat16.as_datatype_enum
    in_functions = {n.op for f in graph_def.library.function for n in f.node_def
                    if any(v.type == bf16 or bf16 in v.list.type for v in n.attr.values())}
    assert in_functions <= {"Cast", "Identity"}, in_functions
    assert all(v.dtype == "float32" for v in m16.variables)
    assert m16.conv_C.conv.compute_dtype == "bfloat16" and m16.upsample_S.u5.compute_dtype == "bfloat16"
    assert m16.point_encoder.compute_dtype == "float32" and m16.head_y.compute_dtype == "float32"


def test_stage_outputs_and_float32_pillar_sums(models):
    """Coordinates, pillar indices and pillar sums are float32 computations: the bfloat16 model's point stage gives
    the float32 model's pillar ids exactly (also for points 0.01 m below a pillar boundary) and its pillar sums
    rounded once to bfloat16 (bfloat16 sums would differ); its convolutions give bfloat16 grids."""
    m32, m16 = models
    inputs = _inputs()
    e32, e16 = m32.encode_points(inputs), m16.encode_points(inputs)
    xyz = inputs["points_xyz_t0"].numpy().astype(np.float64)[0]
    col, row = np.floor((xyz[:, 0] + 40.0) / 2.5), np.floor((xyz[:, 1] + 40.0) / 2.5)
    assert col[:20].tolist() == [30] * 20 and row[20:40].tolist() == [2] * 20  # the cases bfloat16 would move
    want = (row * 32 + col).astype(np.int64)
    valid = e16["point_valid_t0"].numpy()[0]
    assert valid[:-30].all() and not valid[-30:].any()
    np.testing.assert_array_equal(e16["pillar_ids_t0"].numpy()[0][valid], want[valid])
    np.testing.assert_array_equal(e16["pillar_ids_t0"].numpy(), e32["pillar_ids_t0"].numpy())
    assert e32["bev_features"].dtype == tf.float32 and e16["bev_features"].dtype == tf.bfloat16
    assert np.count_nonzero(e32["bev_features"].numpy()) > 100
    np.testing.assert_array_equal(e16["bev_features"].numpy(),
                                  tf.cast(e32["bev_features"], tf.bfloat16).numpy())  # summed in float32
    assert e16["point_flow_t0"].dtype == tf.float32
    np.testing.assert_array_equal(e16["point_flow_t0"].numpy(), e32["point_flow_t0"].numpy())
    grid16 = m16.dense_stages(e16["bev_features"])
    assert grid16.dtype == tf.bfloat16 and m16.conv_C(e16["bev_features"]).dtype == tf.bfloat16
    assert m32.dense_stages(e32["bev_features"]).dtype == tf.float32


def test_bfloat16_outputs_close_to_float32(models):
    """Same weights, mode hybrid, tiny config: the bfloat16 flow within 1% (relative L2) of the float32 flow and within
    3% of the largest flow at every point; the same valid points. (Measured: 0.2% and 0.4%.) Training-mode gradients
    are float32 and within 5% (relative L2) of float32's."""
    m32, m16 = models
    inputs = _inputs()
    a = tf.function(lambda x: m32(x))(inputs)
    b = tf.function(lambda x: m16(x))(inputs)
    assert b["flow_mps"].dtype == tf.float32
    np.testing.assert_array_equal(a["point_valid"].numpy(), b["point_valid"].numpy())
    fa, fb = a["flow_mps"].numpy(), b["flow_mps"].numpy()
    assert 0.1 < np.abs(fa).max() < 50, np.abs(fa).max()  # m/s
    assert np.linalg.norm(fb - fa) < 0.01 * np.linalg.norm(fa), np.linalg.norm(fb - fa) / np.linalg.norm(fa)
    assert np.abs(fb - fa).max() < 0.03 * np.abs(fa).max(), np.abs(fb - fa).max()
    assert np.abs(fb - fa).max() > 0  # the convolutions did run in bfloat16

    def grads(model):
        @tf.function
        def fn(x):
            with tf.GradientTape() as tape:
                loss = tf.reduce_mean(tf.square(model(x, training=True)["flow_mps"] - 1.0))
            return tape.gradient(loss, model.trainable_variables)
        return fn(inputs)
    g32, g16 = grads(m32), grads(m16)
    assert all(g.dtype == tf.float32 for g in g16)
    flat32 = np.concatenate([g.numpy().ravel() for g in g32])
    flat16 = np.concatenate([g.numpy().ravel() for g in g16])
    assert np.linalg.norm(flat16 - flat32) < 0.05 * np.linalg.norm(flat32)
    m16.set_weights(m32.get_weights())  # BatchNorm statistics moved by the training calls; module fixture

"""The execution plan (`ff3d_tf.model.plan`) against the table forward (`FastFlow3D.table_forward`): every field of
the plan, alone and all together, computes the table's flow and the table's gradients of every weight up to float
rounding, eagerly and as one XLA program, with both heads; the plan's rules and checks; the table forward itself
against NumPy on rows W-Z."""
import dataclasses

import keras
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.config import HEADS, replace_config
from ff3d_tf.model import heads
from ff3d_tf.model import build_model
from ff3d_tf.model.plan import FORM_FIELDS, ExecutionPlan, resolve


def _inputs(seed=3, n0=300, n1=260):
    rng = np.random.default_rng(seed)

    def cloud(n):
        xyz = rng.uniform(-38, 38, (1, n, 3)).astype(np.float32)
        xyz[..., 2] = rng.uniform(-2.5, 2.5, (1, n))
        mask = rng.uniform(size=(1, n)) > 0.1  # some masked points
        return tf.constant(xyz), tf.constant(rng.uniform(0, 1, (1, n, 2)).astype(np.float32)), tf.constant(mask)
    p0, f0, m0 = cloud(n0)
    p1, f1, m1 = cloud(n1)
    return {"points_xyz_t0": p0, "point_features_t0": f0, "point_mask_t0": m0,
            "points_xyz_tm1_in_t0": p1, "point_features_tm1": f1, "point_mask_tm1": m1}


def _table_model(cfg):
    """The table model, with a head scaled to flows of about 1 m/s and non-trivial moving statistics (so that
    inference's normalisation and the folded BatchNorm matter)."""
    keras.utils.set_random_seed(11)
    table = build_model(cfg, plan=ExecutionPlan.table(), point_chunk_size=128)
    if cfg.model.head == "paper":
        table.head_z.kernel.assign(table.head_z.kernel * 0.1)
    for v in table.non_trainable_variables:
        if "moving_variance" in v.path:
            v.assign(np.linspace(0.5, 2.0, v.shape[0]).astype(np.float32))
        elif "moving_mean" in v.path:
            v.assign(np.linspace(-0.2, 0.2, v.shape[0]).astype(np.float32))
    return table


def _fused_model(cfg, plan, table):
    fused = build_model(cfg, plan=plan, point_chunk_size=128)
    fused.set_weights(table.get_weights())
    return fused


def _flow_and_gradients(model, inputs, training, how):
    """The flow [1,N0,3] and the gradient of every trainable weight of sum(flow * a fixed projection); `how`: eager,
    graph (each stage as the plan's compile mode traces it) or xla (the whole call one program). The weights are
    restored afterwards (training moves the BatchNorm statistics)."""
    projection = tf.constant(np.random.default_rng(5).normal(size=(1, inputs["points_xyz_t0"].shape[1], 3))
                             .astype(np.float32))

    def run(x):
        with tf.GradientTape() as tape:
            flow = model(x, training=training, inline_stages=how == "xla")["flow_mps"]
            loss = tf.reduce_sum(flow * projection)
        return [flow] + tape.gradient(loss, model.trainable_variables)
    weights = model.get_weights()
    out = run(inputs) if how == "eager" else tf.function(run, jit_compile=how == "xla")(inputs)
    model.set_weights(weights)
    return [t.numpy() for t in out]


def _assert_same(got, want, variables, what):
    np.testing.assert_allclose(got[0], want[0], rtol=1e-4, atol=1e-4 * np.abs(want[0]).max(), err_msg=f"{what}: flow")
    assert np.abs(want[0]).max() > 1e-3, what
    for g, w, v in zip(got[1:], want[1:], variables):
        if v.path.endswith("mlp/hidden_bias") and "inference" not in what:
            # A bias right before a BatchNorm on the batch's statistics cancels in training: its gradient is 0, and
            # both forwards give float rounding of 0 (about 1e-6 here), which no relative tolerance compares.
            assert max(np.abs(g).max(), np.abs(w).max()) < 1e-4, f"{what}: {v.path}"
            continue
        np.testing.assert_allclose(g, w, atol=2e-4 * np.abs(w).max() + 1e-7, err_msg=f"{what}: {v.path}")


def _one_form(name):
    """A fused plan with only `name` on (decoder_chain with the head it composes with)."""
    forms = {f: f == name for f in FORM_FIELDS}
    if name == "decoder_chain":
        forms["v_with_head"] = True
    return ExecutionPlan(compile_mode="none", **forms)


EVERY_FORM = ExecutionPlan(compile_mode="none", matmul_1x1=True, stride2_phase_gradients=True,
                           u6_into_next_u1=True, v_with_head=True, decoder_chain=True, remat_encoder=True)
COMPOSING_ONLY = ("v_with_head", "decoder_chain")  # forms of a head whose first layer composes with row V


@pytest.mark.parametrize("head,each_form", [(head, False) for head in HEADS] +
                         [pytest.param(head, True, marks=pytest.mark.slow) for head in HEADS])
def test_each_form_computes_the_table_in_training(tiny_config, head, each_form):
    """Training (BatchNorm on the batch's statistics, remat_encoder's recomputation): every form together, and in
    make test-slow each form alone, against the table: the flow and every weight's gradient, eagerly and as one XLA
    program (each XLA compilation of the tiny model's step costs seconds; the plans training resolves are also run in
    make test: all forms here, hybrid's below)."""
    cfg = replace_config(tiny_config, {"model.head": head, "model.gru_iterations": 1})
    table = _table_model(cfg)
    want = {how: _flow_and_gradients(table, _inputs(), True, how) for how in ("eager", "xla")}
    composes = heads.HEADS[head].composes_with_v
    forms = [f for f in FORM_FIELDS if f != "fold_batch_norm" and (composes or f not in COMPOSING_ONLY)]
    for form in ["all"] + (forms if each_form else []):
        plan = EVERY_FORM if form == "all" else _one_form(form)
        if not composes:  # the head reads row V's channels themselves: no form of the paper head's rows V-Z
            plan = plan.replace(v_with_head=False, decoder_chain=False)
        fused = _fused_model(cfg, plan, table)
        for how in ("eager", "xla"):
            _assert_same(_flow_and_gradients(fused, _inputs(), True, how), want[how], table.trainable_variables,
                         f"{head}/{form}/{how}")


@pytest.mark.parametrize("head", HEADS)
def test_folded_batch_norm_and_every_inference_form_compute_the_table(tiny_config, head):
    """Inference (moving statistics): the inference plan's forms with the BatchNorm folded into each ConvBlock,
    eagerly and as one XLA program."""
    cfg = replace_config(tiny_config, {"model.head": head, "model.gru_iterations": 1})
    table = _table_model(cfg)
    fused = _fused_model(cfg, resolve(cfg.model, "inference", "none")[0].replace(fold_batch_norm=True), table)
    for how in ("eager", "xla"):
        want = _flow_and_gradients(table, _inputs(), False, how)
        _assert_same(_flow_and_gradients(fused, _inputs(), False, how), want, table.trainable_variables,
                     f"{head}/inference/{how}")


@pytest.mark.parametrize("programs", ["per_cloud", "one"])
def test_hybrid_point_programs_compute_the_table(tiny_config, programs):
    """Compile mode hybrid's staging (the point stages as XLA programs of their own, `point_programs`), traced as the
    trainer traces it: the table's flow and gradients."""
    table = _table_model(tiny_config)
    plan = resolve(tiny_config.model, "train", "hybrid", "CPU")[0].replace(point_programs=programs)
    want = _flow_and_gradients(table, _inputs(), True, "graph")
    _assert_same(_flow_and_gradients(_fused_model(tiny_config, plan, table), _inputs(), True, "graph"), want,
                 table.trainable_variables, programs)


def test_table_forward_rows_w_to_z_by_hand(tiny_config):
    """Rows W-Z of the table forward by NumPy from row V's grid and row A's features: each valid t0 point takes its
    pillar's cell (W), concatenated with its point feature and 8-D encoding (X), through Y's kernel and bias and
    Z's; invalid points get 0."""
    keras.utils.set_random_seed(2)
    model = build_model(tiny_config, plan=ExecutionPlan.table())
    inputs = _inputs(seed=4, n0=200, n1=150)
    captured = {}
    original = model.conv_v.call

    def capture_v(x):  # row V's output, as the forward computes it
        captured["v"] = original(x)
        return captured["v"]
    model.conv_v.call = capture_v
    flow = model(inputs)["flow_mps"].numpy()[0]
    encoding_t0, ids_t0, valid_t0 = model.pillarize(inputs["points_xyz_t0"], inputs["point_features_t0"],
                                                    inputs["point_mask_t0"])
    encoding_tm1, _, valid_tm1 = model.pillarize(inputs["points_xyz_tm1_in_t0"], inputs["point_features_tm1"],
                                                 inputs["point_mask_tm1"])
    features = model.point_encoder.point_features([encoding_t0, encoding_tm1], [valid_t0, valid_tm1])[0]
    encoding, ids, valid, features = (t.numpy()[0] for t in (encoding_t0, ids_t0, valid_t0, features))
    v = captured["v"].numpy().reshape(-1, captured["v"].shape[-1])
    x = np.concatenate([v[np.minimum(ids, len(v) - 1)], features, encoding], -1)  # W, X
    y = x @ model.head_y.kernel.numpy() + model.head_y.bias.numpy()  # Y
    z = y @ model.head_z.kernel.numpy() + model.head_z.bias.numpy()  # Z
    expected = np.where(valid[:, None], z, 0.0)
    assert valid.sum() > 100 and not valid.all()
    np.testing.assert_allclose(flow, expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())


def test_the_resolved_plans_rules(tiny_config):
    """The fused forms per job and device (module docstring of ff3d_tf.model.plan), the table plan, and the config's
    remat_encoder and forward keys."""
    m = tiny_config.model
    train_xla = resolve(m, "train", "xla", "CPU")[0]
    assert train_xla.stride2_phase_gradients and train_xla.decoder_chain and train_xla.matmul_1x1
    train_hybrid = resolve(m, "train", "hybrid", "CPU")[0]
    assert not train_hybrid.stride2_phase_gradients and not train_hybrid.decoder_chain and train_hybrid.v_with_head
    assert resolve(m, "inference", "hybrid", "CPU")[0].decoder_chain
    assert not resolve(m, "train", "xla", "GPU")[0].stride2_phase_gradients
    gru = resolve(dataclasses.replace(m, head="gru"), "inference", "none", "CPU")[0]
    assert not gru.v_with_head and not gru.decoder_chain
    assert resolve(dataclasses.replace(m, remat_encoder=True), "train", "xla", "CPU")[0].remat_encoder
    table = resolve(dataclasses.replace(m, forward="table", remat_encoder=True), "train", "xla", "CPU")[0]
    assert table == ExecutionPlan.table("xla") and not any(getattr(table, f) for f in FORM_FIELDS)


def test_a_plan_is_checked_and_recorded(tiny_config):
    with pytest.raises(ValueError, match="apply to forward=fused only"):
        ExecutionPlan(forward="table")
    with pytest.raises(ValueError, match="v_with_head=true"):
        ExecutionPlan(v_with_head=False, decoder_chain=True)
    with pytest.raises(ValueError, match="decoder_chain computes in float32"):
        ExecutionPlan(precision="bfloat16", decoder_chain=True)
    with pytest.raises(ValueError, match="unknown field"):
        ExecutionPlan.from_dict({"convolution_forms": "plain"})
    with pytest.raises(ValueError, match="true or false"):
        ExecutionPlan(matmul_1x1="yes")
    model = build_model(tiny_config, "xla", job="train")
    config = model.get_config()
    assert ExecutionPlan.from_dict(config["plan"]) == model.plan == resolve(tiny_config.model, "train", "xla")[0]
    assert "forms: matmul_1x1" in model.plan.describe()
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.plan.matmul_1x1 = False

"""SeFlow's and TeFlow's losses against NumPy references written from the authors' formulas (KTH-RPL/OpenSceneFlow
src/lossfuncs/selfsupervise.py: loops over samples and clusters, brute-force nearest neighbours), and the loss table
that the config, the input and the step read."""
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.config import LOSS_SPECS, ConfigError, SelfSupConfig, load_config
from ff3d_tf.model import losses, selfsup_losses
from ff3d_tf.training import input as training_input

DT = 0.1


def _cloud(rng, shift, n_ground=200, n_static=150, n_cluster=160, n_noise=8):
    """Points and labels (-2 ground, -1 static, 0 noise, k cluster): a ground plane, static clutter, two clusters."""
    ground = np.c_[rng.uniform(-15, 15, (n_ground, 2)), rng.normal(0, 0.02, n_ground)]
    static = rng.uniform([-15, -15, 0.5], [15, 15, 3], (n_static, 3))
    c1 = rng.normal([5, 2, 1], 0.4, (n_cluster, 3)) + shift[0]
    c2 = rng.normal([-4, -6, 1], 0.3, (n_cluster, 3)) + shift[1]
    noise = rng.uniform(-15, 15, (n_noise, 3))
    xyz = np.concatenate([ground, static, c1, c2, noise]).astype(np.float32)
    label = np.concatenate([np.full(n_ground, -2), np.full(n_static, -1), np.full(n_cluster, 1),
                            np.full(n_cluster, 2), np.zeros(n_noise)]).astype(np.int32)
    return xyz, label


def _batch(seed=0, num_clouds=2, pad=16):
    """Two samples; every cloud padded by `pad` points that the masks leave out (and a t0 point the model marks
    invalid)."""
    rng = np.random.default_rng(seed)
    samples = []
    for _ in range(2):
        motion = rng.normal(0, 0.5, (2, 3)) * [1, 1, 0]
        clouds = [_cloud(rng, -k * motion) for k in range(num_clouds)]
        samples.append(clouds)
    batch, real = {}, {}
    for i, cloud in enumerate(schema.sweep_clouds(num_clouds)):
        n = max(len(s[i][0]) for s in samples) + pad
        xyz = np.zeros((2, n, 3), np.float32)
        label = np.full((2, n), -1, np.int32)
        mask = np.zeros((2, n), bool)
        for b, s in enumerate(samples):
            xyz[b, :len(s[i][0])], label[b, :len(s[i][0])], mask[b, :len(s[i][0])] = s[i][0], s[i][1], True
        xyz[~mask] = 99.0  # padding far away: it would be everyone's nearest neighbour's rival if it counted
        keys = schema.cloud_keys(cloud)
        batch[keys["xyz"]], batch[keys["mask"]] = xyz, mask
        batch[schema.DYNAMIC_CLUSTER_KEY_FORMAT.format(cloud=cloud)] = label
        real[cloud] = mask
    flow = (rng.normal(0, 3, batch["points_xyz_t0"].shape)).astype(np.float32)
    point_valid = np.ones(real["t0"].shape, bool)
    point_valid[:, 3] = False
    return batch, flow, point_valid


def _nn(a, b):
    d = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return d.min(1), d.argmin(1)


def _np_chamfer(a, b, truncate):
    if not len(a) or not len(b):
        return 0.0
    da, _ = _nn(a, b)
    db, _ = _nn(b, a)
    keep_a, keep_b = da[da <= truncate], db[db <= truncate]
    return (keep_a.mean() if len(keep_a) else 0.0) + (keep_b.mean() if len(keep_b) else 0.0)


def _sample(batch, flow, point_valid, b, cloud):
    keys = schema.cloud_keys(cloud)
    mask = batch[keys["mask"]][b] & (point_valid[b] if cloud == "t0" else True)
    label = batch[schema.DYNAMIC_CLUSTER_KEY_FORMAT.format(cloud=cloud)][b]
    return batch[keys["xyz"]][b], label, mask


def np_self_supervised(batch, flow, point_valid, partner, temporal, w=(1.0, 1.0, 1.0, 1.0)):
    """The batch's loss, sample by sample as the authors' loops (the differences docs/label_free.md names: each
    term a mean over samples, ground in the static term, the partner's Chamfer weight 1)."""
    num_clouds = 3 if "points_xyz_tm2_in_t0" in batch else 2
    clouds = schema.sweep_clouds(num_clouds if temporal else 2)
    offsets = selfsup_losses.sweep_offsets(len(clouds), partner)
    sign = -1.0 if partner == "next" else 1.0
    totals = []
    for b in range(2):
        p0, l0, m0 = _sample(batch, flow, point_valid, b, "t0")
        v_all = flow[b] * sign * DT
        keep0 = m0 & (l0 != -2)
        P0, L0, V = p0[keep0], l0[keep0], v_all[keep0]
        dyn0 = L0 >= 1  # the authors' label > 0: in a cluster
        static = np.linalg.norm(v_all[m0 & ~((l0 >= 1) & (l0 != -2))], axis=1).mean()
        chamfer = dynamic = 0.0
        others = []
        for k, (cloud, o) in enumerate(zip(clouds[1:], offsets)):
            pk, lk, mk = _sample(batch, flow, point_valid, b, cloud)
            keep = mk & (lk != -2)
            Pk, Lk = pk[keep], lk[keep]
            others.append((Pk, Lk, o))
            weight = 1.0 if (not temporal or k == 0) else 0.5 ** abs(o)
            moved = P0 + o * V
            chamfer += weight * _np_chamfer(moved, Pk, 4.0 * abs(o))
            if dyn0.sum() > 256 and (Lk >= 1).sum() > 256:
                dynamic += weight * _np_chamfer(moved[dyn0], Pk[Lk >= 1], 4.0 * abs(o))
        chamfer, dynamic = chamfer / len(others), dynamic / len(others)
        cluster = (np_teflow_cluster(P0, L0, V, others) if temporal else np_seflow_cluster(P0, L0, V, others[0]))
        totals.append(w[0] * chamfer + w[1] * dynamic + w[2] * static + w[3] * cluster)
    return float(np.mean(totals))


def np_seflow_cluster(P0, L0, V, partner):
    P1, L1, o = partner
    if not ((L0 >= 1).sum() > 256 and (L1 >= 1).sum() > 256):
        return 0.0
    dist0, idx0 = _nn(P0, P1)
    norms = []
    for c in np.unique(L0[L0 >= 1]):
        mask = L0 == c
        order = np.argsort(-dist0[mask], kind="stable")
        hits = np.flatnonzero(L1[idx0[mask][order]] >= 1)
        if not len(hits):
            continue
        best = order[hits[0]]
        target = (P1[idx0[mask][best]] - P0[mask][best]) / o  # Eq. 9, displacement over one sweep forward
        norms.append(np.linalg.norm(V[mask] - target, axis=1))
    return float(np.concatenate(norms).mean()) if norms else 0.0


def np_teflow_cluster(P0, L0, V, others, top_k=5, cos_threshold=0.7071, decay=0.9):
    cluster_points, targets, cluster_means = [], [], []
    nn = [(_nn(P0, Pk), o) for Pk, _, o in others]
    for c in np.unique(L0[L0 >= 1]):
        mask = L0 == c
        if mask.sum() <= top_k:
            continue
        flows, dists, votes = [], [], []
        for (dist, idx), o in nn:
            dc, ic = dist[mask], idx[mask]
            top = np.argsort(-dc, kind="stable")[:top_k]
            Pk = others[[x[2] for x in others].index(o)][0]
            flows.append((Pk[ic[top]] - P0[mask][top]) / o)  # Eq. 3
            dists.append(dc[top])
            votes.append(np.full(top_k, decay ** abs(o)))
        mean_v = V[mask].mean(0)  # Eq. 2
        cands = np.concatenate(flows + [mean_v[None]])  # Eq. 4
        d = np.concatenate(dists + [[np.linalg.norm(mean_v)]])
        d_norm = (d - d.min()) / (d.max() - d.min() + 1e-6)
        norms = np.linalg.norm(cands, axis=1)
        cos = cands @ cands.T / np.maximum(norms[:, None] * norms[None, :], 1e-8)  # Eq. 5
        inlier = cos > cos_threshold
        weights = np.concatenate(votes + [[1.0]]) * (1 + d_norm)  # Eq. 6
        best = np.argmax(inlier.astype(float) @ weights)  # Eq. 7
        w = weights[inlier[best]]
        target = (w[:, None] * cands[inlier[best]]).sum(0) / w.sum()  # Eq. 8
        cluster_points.append(V[mask])
        targets.append(np.broadcast_to(target, V[mask].shape))
        cluster_means.append(np.linalg.norm(V[mask] - target, axis=1).mean())
    if not cluster_points:
        return 0.0
    point_term = ((np.concatenate(cluster_points) - np.concatenate(targets)) ** 2).mean()  # Eq. 9, mse per element
    return float(point_term + np.mean(cluster_means))


def _tf_loss(batch, flow, point_valid, loss, partner, selfsup=SelfSupConfig()):
    tf_batch = {k: tf.constant(v) for k, v in batch.items()}
    outputs = {"flow_mps": tf.constant(flow), "point_valid": tf.constant(point_valid)}
    context = losses.LossContext("self", 0.1, selfsup, partner)
    return losses.batch_flow_loss(tf_batch, outputs, 0.1, 2, loss=loss, context=context)


@pytest.mark.parametrize("partner", ["previous", "next"])
def test_seflow_matches_the_authors_formulas(partner):
    batch, flow, point_valid = _batch(seed=1)
    want = np_self_supervised(batch, flow, point_valid, partner, temporal=False)
    got = float(_tf_loss(batch, flow, point_valid, "seflow", partner))
    np.testing.assert_allclose(got, want, rtol=2e-4)


@pytest.mark.parametrize("partner", ["previous", "next"])
def test_teflow_over_three_sweeps_matches_the_authors_formulas(partner):
    batch, flow, point_valid = _batch(seed=2, num_clouds=3)
    want = np_self_supervised(batch, flow, point_valid, partner, temporal=True)
    got = float(_tf_loss(batch, flow, point_valid, "teflow", partner))
    np.testing.assert_allclose(got, want, rtol=2e-4)


@pytest.mark.parametrize("loss", ["seflow", "teflow"])
def test_every_term_counts_in_the_references(loss):
    """The batches above exercise every term: each weighted alone is positive (and matches its reference)."""
    batch, flow, point_valid = _batch(seed=2, num_clouds=3)
    for i in range(4):
        w = tuple(float(j == i) for j in range(4))
        selfsup = SelfSupConfig(*w)
        want = np_self_supervised(batch, flow, point_valid, "next", loss == "teflow", w)
        assert want > 0, (loss, i)
        np.testing.assert_allclose(float(_tf_loss(batch, flow, point_valid, loss, "next", selfsup)), want,
                                   rtol=2e-4)


def test_term_weights_scale_their_terms():
    # Only the static term (weight 2): 2 x the mean |v| of the t0 points that are not in a cluster, by hand in NumPy.
    batch, flow, point_valid = _batch(seed=3)
    selfsup = SelfSupConfig(chamfer_weight=0.0, dynamic_chamfer_weight=0.0, static_flow_weight=2.0,
                            cluster_weight=0.0)
    got = float(_tf_loss(batch, flow, point_valid, "seflow", "previous", selfsup))
    per_sample = [np.linalg.norm(flow[b][batch["point_mask_t0"][b] & point_valid[b] &
                                         (batch["dynamic_cluster_t0"][b] < 1)] * DT, axis=1).mean() for b in range(2)]
    np.testing.assert_allclose(got, 2.0 * np.mean(per_sample), rtol=1e-5)


def test_truncated_chamfer_by_hand():
    # a = {(0,0,0), (10,0,0)}, b = {(1,0,0)}: a->b squared 1 and 81 (81 > 4: left out) -> 1; b->a: 1 -> total 2.
    a = tf.constant([[[0.0, 0, 0], [10, 0, 0], [5, 5, 5]]])
    b = tf.constant([[[1.0, 0, 0], [7, 7, 7]]])
    got = selfsup_losses.truncated_chamfer(a, tf.constant([[True, True, False]]), b, tf.constant([[True, False]]), 4.0)
    np.testing.assert_allclose(got.numpy(), [2.0], rtol=1e-6)


def test_nearest_indices_against_brute_force_across_blocks():
    rng = np.random.default_rng(4)
    q = rng.uniform(-30, 30, (2, 700, 3)).astype(np.float32)  # 3 blocks of 256 queries
    t = rng.uniform(-30, 30, (2, 300, 3)).astype(np.float32)
    t_mask = rng.random((2, 300)) < 0.7
    got = selfsup_losses.nearest_indices(tf.constant(q), tf.ones([2, 700], bool), tf.constant(t),
                                         tf.constant(t_mask)).numpy()
    for b in range(2):
        allowed = np.flatnonzero(t_mask[b])
        _, idx = _nn(q[b], t[b][allowed])
        np.testing.assert_array_equal(got[b], allowed[idx])


@pytest.mark.parametrize("loss", ["seflow", "teflow"])
def test_gradients_finite_and_xla_agrees(loss):
    batch, flow, point_valid = _batch(seed=5, num_clouds=3)
    tf_batch = {k: tf.constant(v) for k, v in batch.items()}
    context = losses.LossContext("self", 0.1, SelfSupConfig(), "next")

    def loss_and_grad(flow_mps):
        with tf.GradientTape() as tape:
            tape.watch(flow_mps)
            value = losses.batch_flow_loss(tf_batch, {"flow_mps": flow_mps, "point_valid": tf.constant(point_valid)},
                                           0.1, 2, loss=loss, context=context)
        return value, tape.gradient(value, flow_mps)

    eager_loss, eager_grad = loss_and_grad(tf.constant(flow))
    xla_loss, xla_grad = tf.function(loss_and_grad, jit_compile=True)(tf.constant(flow))
    np.testing.assert_allclose(xla_loss.numpy(), eager_loss.numpy(), rtol=1e-4)
    np.testing.assert_allclose(xla_grad.numpy(), eager_grad.numpy(), rtol=1e-3, atol=1e-6)
    assert np.isfinite(eager_grad.numpy()).all() and np.abs(eager_grad.numpy()).sum() > 0
    assert np.all(eager_grad.numpy()[~(batch["point_mask_t0"] & point_valid)] == 0)  # padding and invalid: none


def test_loss_table_ties_config_functions_and_schema():
    assert set(losses.LOSS_FUNCTIONS) == set(LOSS_SPECS)
    for name, spec in LOSS_SPECS.items():
        for which in ("needs", "may_use"):
            for key in spec.fields(which, schema.MAX_NUM_FRAMES):
                assert key in schema.POINT_KEYS and schema.POINT_KEYS[key].optional, (name, key)
    assert LOSS_SPECS["teflow"].fields("needs", 3) == ("dynamic_cluster_t0", "dynamic_cluster_tm1",
                                                       "dynamic_cluster_tm2")
    assert LOSS_SPECS["seflow"].fields("needs", 3) == ("dynamic_cluster_t0", "dynamic_cluster_tm1")


def test_config_pairs_labels_and_losses():
    records = ["data.source=pair_records"]
    assert load_config(None, records + ["data.labels=self", "train.loss=teflow", "data.num_frames=3",
                                        "model.temporal=stack"]).train.loss == "teflow"
    with pytest.raises(ConfigError, match="data.labels=self use train.loss=seflow or teflow"):
        load_config(None, records + ["data.labels=self"])
    # human labels with seflow: the config of evaluating a self-supervised model (evaluation scores human labels);
    # training refuses it before any work
    evaluating = load_config(None, ["train.loss=seflow"])
    with pytest.raises(ConfigError, match="train.loss=seflow trains on data.labels self, not human"):
        training_input.loss_extras(["unused"], evaluating)
    with pytest.raises(ConfigError, match="data.labels=self: its fields live in pair records"):
        load_config(None, ["data.labels=self", "train.loss=seflow"])
    with pytest.raises(ConfigError, match="selfsup.sweep_period_s"):
        load_config(None, ["selfsup.sweep_period_s=0"])
    with pytest.raises(ValueError, match="trains on self labels, not human"):
        losses.per_sample_training_loss({}, {}, 0.1, loss="seflow")

"""Self-supervised losses without flow labels: SeFlow's (Zhang et al., "SeFlow: A Self-Supervised Scene Flow Method in
Autonomous Driving", ECCV 2024, arXiv 2407.01702) over the pair, and TeFlow's (arXiv 2602.19053) over every sweep of
the example. `train.loss=seflow` / `teflow` with `data.labels=self`; the per-point fields they read are written by
`tools/prepare_self_supervision.py` (`schema.DYNAMIC_CLUSTER_KEY_FORMAT`: ground, static, dynamic, cluster).

Facts read in KTH-RPL/OpenSceneFlow @848bf86 (src/lossfuncs/selfsupervise.py: seflowLoss, teflowLoss and their
helpers; assets/cuda/chamfer3D/__init__.py: the truncated Chamfer; src/autolabel.py: seflow_auto; src/dataset.py:
ground removed from every cloud); docs/label_free.md names each formula's file and line and where this differs. No
code copied. In brief (B samples, each its own loss, the batch's the mean over samples):

- Flow is the model's (m/s, `flow_mps_t0`'s convention); v = s * flow * `selfsup.sweep_period_s` is the t0 point's
  displacement over one sweep forward in time (s = +1 when the partner is the previous sweep, -1 when it is the next:
  the flow is then minus the velocity). A cloud of the example `o` sweeps from t0 (partner previous: tm_k at -k;
  partner next: tm1 at +1, tm_k at -(k - 1)) is matched by p0 + o v.
- "Dynamic" is the authors' label > 0: a point in a DUFOMap-dynamic cluster (HDBSCAN's noise counts as static, as
  seflow_auto makes it). Ground points take part in no term but the static one (the authors remove them from every
  cloud; here the model predicts them, and they are static).
- Chamfer: the truncated two-sided Chamfer of squared distances, points farther than `TRUNCATED_SQ_DIST_M2` x |o|
  (squared) left out of each side's mean.
- Dynamic Chamfer: the same between the dynamic points of t0 (moved) and of the other cloud, where both have more
  than `MIN_DYNAMIC_POINTS`.
- Static: the mean |v| of the t0 points that are not dynamic.
- SeFlow's cluster term: each cluster's target is the displacement from its t0 point farthest from the partner cloud
  whose nearest partner point is dynamic; the mean |v - target| over the clusters' points.
- TeFlow's: every sweep's Chamfer terms weighted (the partner 1, as the authors' future sweep; the others 1 / 2^|o|)
  and averaged; each cluster's target voted among candidate displacements (the `TEFLOW_TOP_K` points farthest from
  each sweep, and the cluster's mean prediction); the mean squared error per coordinate plus the mean error per
  cluster.
"""
from __future__ import annotations

import tensorflow as tf

from ff3d_tf import schema

TRUNCATED_SQ_DIST_M2 = 4.0  # squared metres per sweep of offset (the authors' TRUNCATED_DIST)
MIN_DYNAMIC_POINTS = 256  # a cloud's dynamic points count for the dynamic terms only above this many
TEFLOW_TOP_K = 5  # candidates per cluster and sweep
TEFLOW_COS_THRESHOLD = 0.7071  # two candidates agree above this cosine
TEFLOW_TIME_DECAY = 0.9  # a sweep |o| sweeps away votes with TEFLOW_TIME_DECAY^|o|
TEFLOW_NETWORK_WEIGHT = 1.0  # the cluster's mean prediction votes with this weight
_NN_CHUNK = 256  # query points per block of the nearest-neighbour search
_FAR = 1e30


def sweep_offsets(num_frames: int, partner: str | None) -> tuple[int, ...]:
    """The time of each cloud tm1, tm2, ... of an example of `num_frames` sweeps from t0, in sweeps
    (`schema.slot_sweep_offsets`; `partner` None reads as "previous")."""
    return schema.slot_sweep_offsets(num_frames, partner or "previous")[1:]


def forward_displacement_m(flow_mps, partner: str | None, sweep_period_s: float):
    """[B,N,3] v: each t0 point's displacement over one sweep forward in time (m), from the model's flow (m/s)."""
    sign = -1.0 if partner == "next" else 1.0
    return tf.cast(flow_mps, tf.float32) * (sign * sweep_period_s)


def nearest_indices(query_xyz, query_mask, target_xyz, target_mask):
    """[B,N] int32: the index of each query point's nearest target point among those of `target_mask` (exact, blocks
    of `_NN_CHUNK` queries against every target: [B, chunk, M] at a time); arbitrary where the sample has no target
    point. No gradient: callers gather the matched points and take distances with gradients themselves."""
    del query_mask  # every query gets an index; the caller masks
    query_xyz, target_xyz = tf.stop_gradient(query_xyz), tf.stop_gradient(target_xyz)
    weights = tf.cast(target_mask, tf.float32)[..., None]
    centre = tf.reduce_sum(target_xyz * weights, 1, keepdims=True) / tf.maximum(tf.reduce_sum(weights, 1, True), 1.0)
    query, target = query_xyz - centre, target_xyz - centre  # smaller norms: a finer |q|^2 - 2 q.t + |t|^2
    b, n = tf.shape(query)[0], tf.shape(query)[1]
    pad = (-n) % _NN_CHUNK
    blocks = tf.transpose(tf.reshape(tf.pad(query, [[0, 0], [0, pad], [0, 0]]), [b, -1, _NN_CHUNK, 3]), [1, 0, 2, 3])
    target_sq = tf.reduce_sum(tf.square(target), -1) + tf.where(target_mask, 0.0, _FAR)  # [B,M]

    def block_argmin(block):  # [B,K,3] -> [B,K]
        sq = (tf.reduce_sum(tf.square(block), -1)[..., None] - 2.0 * tf.matmul(block, target, transpose_b=True)
              + target_sq[:, None, :])
        return tf.argmin(sq, -1, output_type=tf.int32)

    found = tf.map_fn(block_argmin, blocks, fn_output_signature=tf.TensorSpec([None, None], tf.int32))
    return tf.reshape(tf.transpose(found, [1, 0, 2]), [b, -1])[:, :n]


def _gather(points, index):
    return tf.gather(points, index, batch_dims=1)


def _masked_mean(values, mask):
    """[B] mean of `values` [B,N] over `mask`; 0 where the mask is empty."""
    m = tf.cast(mask, tf.float32)
    return tf.reduce_sum(values * m, -1) / tf.maximum(tf.reduce_sum(m, -1), 1.0)


def truncated_chamfer(a_xyz, a_mask, b_xyz, b_mask, truncate_sq_m2: float):
    """[B] the two-sided Chamfer of squared distances: the mean over the points of `a` of the squared distance to
    their nearest point of `b`, those at more than `truncate_sq_m2` left out, plus the same from `b` to `a`; a side
    with no point kept adds 0. Gradients reach both clouds' points."""
    both = tf.reduce_any(a_mask, -1, keepdims=True) & tf.reduce_any(b_mask, -1, keepdims=True)
    sq_a = tf.reduce_sum(tf.square(a_xyz - _gather(b_xyz, nearest_indices(a_xyz, a_mask, b_xyz, b_mask))), -1)
    sq_b = tf.reduce_sum(tf.square(b_xyz - _gather(a_xyz, nearest_indices(b_xyz, b_mask, a_xyz, a_mask))), -1)
    return (_masked_mean(sq_a, a_mask & both & (sq_a <= truncate_sq_m2)) +
            _masked_mean(sq_b, b_mask & both & (sq_b <= truncate_sq_m2)))


class _Clouds:
    """One batch's clouds as the losses see them: t0 (its points, those the loss counts, its labels) and every other
    cloud (points in the t0 frame, non-ground real points, labels, offset in sweeps)."""

    def __init__(self, batch, outputs, num_clouds: int, partner: str | None):
        key = schema.DYNAMIC_CLUSTER_KEY_FORMAT.format
        self.p0 = batch["points_xyz_t0"]
        self.label0 = tf.cast(batch[key(cloud="t0")], tf.int32)
        self.real0 = outputs["point_valid"] & batch["point_mask_t0"]
        self.valid0 = self.real0 & (self.label0 != schema.DYNAMIC_CLUSTER_GROUND)
        self.dynamic0 = self.valid0 & (self.label0 > schema.DYNAMIC_CLUSTER_NOISE)
        self.others = []
        clouds = schema.sweep_clouds(num_clouds)[1:]
        for cloud, offset in zip(clouds, sweep_offsets(num_clouds, partner)):
            keys = schema.cloud_keys(cloud)
            label = tf.cast(batch[key(cloud=cloud)], tf.int32)
            valid = batch[keys["mask"]] & (label != schema.DYNAMIC_CLUSTER_GROUND)
            self.others.append((batch[keys["xyz"]], valid, valid & (label > schema.DYNAMIC_CLUSTER_NOISE), offset))


def _count(mask):
    return tf.reduce_sum(tf.cast(mask, tf.int32), -1)


def _chamfer_terms(c: _Clouds, v, weighted: bool):
    """([B] Chamfer, [B] dynamic Chamfer): over the other clouds, each weighted (TeFlow: the partner 1, as the authors'
    future sweep, every other sweep 1 / 2^|o|; SeFlow's single cloud 1) and their sum divided by their number."""
    chamfer = dynamic = 0.0
    for index, (xyz, valid, dynamic_mask, offset) in enumerate(c.others):
        weight = 1.0 if not weighted or index == 0 else 0.5 ** abs(offset)
        moved = c.p0 + float(offset) * v
        truncate = TRUNCATED_SQ_DIST_M2 * abs(offset)
        chamfer += weight * truncated_chamfer(moved, c.valid0, xyz, valid, truncate)
        enough = (_count(c.dynamic0) > MIN_DYNAMIC_POINTS) & (_count(dynamic_mask) > MIN_DYNAMIC_POINTS)
        dynamic += weight * tf.where(enough, truncated_chamfer(moved, c.dynamic0, xyz, dynamic_mask, truncate), 0.0)
    return chamfer / len(c.others), dynamic / len(c.others)


def _static_term(c: _Clouds, v):
    """[B] the mean |v| (m) of the t0 points that are not dynamic (static, HDBSCAN's noise, ground)."""
    return _masked_mean(tf.sqrt(tf.reduce_sum(tf.square(v), -1) + 1e-12), c.real0 & ~c.dynamic0)


def _segments(c: _Clouds, in_cluster, min_points: int):
    """(segment id [B,N] of each t0 point's (sample, cluster), the number of segments): one per cluster id of each
    sample below N // min_points + 1 (HDBSCAN's clusters have at least `min_points` points), the last for the
    points of none."""
    b, n = tf.shape(c.p0)[0], tf.shape(c.p0)[1]
    per_sample = n // min_points + 1
    ok = in_cluster & (c.label0 < per_sample)
    num = b * per_sample
    return tf.where(ok, tf.range(b)[:, None] * per_sample + c.label0, num), num


def seflow_cluster_term(c: _Clouds, v, min_points: int):
    """[B] SeFlow's cluster term: over the samples with enough dynamic points in t0 and in the partner, each cluster's
    target is p_partner[j] - p0[i] over the partner's offset, i its point farthest from the partner cloud (squared
    distance to its nearest non-ground partner point j) among those whose j is dynamic; the mean |v - target| of the
    points of the clusters that have such a point."""
    partner_xyz, partner_valid, partner_dynamic, offset = c.others[0]
    nn = nearest_indices(c.p0, c.valid0, partner_xyz, partner_valid)
    matched = _gather(partner_xyz, nn)
    sq = tf.reduce_sum(tf.square(c.p0 - matched), -1)
    enough = (_count(c.dynamic0) > MIN_DYNAMIC_POINTS) & (_count(partner_dynamic) > MIN_DYNAMIC_POINTS)
    in_cluster = c.dynamic0 & enough[:, None]
    segment, num = _segments(c, in_cluster, min_points)
    flat_segment = tf.reshape(segment, [-1])
    eligible = tf.reshape(in_cluster & _gather(partner_dynamic, nn), [-1])
    score = tf.where(eligible, tf.reshape(sq, [-1]), -1.0)
    best_score = tf.math.unsorted_segment_max(score, flat_segment, num + 1)
    position = tf.range(tf.size(flat_segment))
    is_best = eligible & (score >= tf.gather(best_score, flat_segment))
    best = tf.math.unsorted_segment_min(tf.where(is_best, position, tf.size(flat_segment)), flat_segment, num + 1)
    has_target = tf.gather(best, flat_segment) < tf.size(flat_segment)
    best_point = tf.minimum(tf.gather(best, flat_segment), tf.size(flat_segment) - 1)
    target = tf.gather(tf.reshape(tf.stop_gradient(matched - c.p0), [-1, 3]), best_point) / float(offset)
    error = tf.sqrt(tf.reduce_sum(tf.square(tf.reshape(v, [-1, 3]) - target), -1) + 1e-12)
    counted = tf.reshape(in_cluster, [-1]) & has_target
    return _masked_mean(tf.reshape(error, tf.shape(sq)), tf.reshape(counted, tf.shape(sq)))


def _top_k_per_segment(values, segment, num_segments, k: int):
    """[num_segments, k] the flat positions of each segment's k largest `values` (flat [P]; ties to the lower
    position), -1 where the segment has fewer; `segment` == num_segments: in none."""
    by_value = tf.argsort(values, direction="DESCENDING", stable=True)
    order = tf.gather(by_value, tf.argsort(tf.gather(segment, by_value), stable=True))
    sorted_segment = tf.gather(segment, order)
    sizes = tf.math.unsorted_segment_sum(tf.ones_like(segment), segment, num_segments + 1)
    starts = tf.cumsum(sizes, exclusive=True)
    rank = tf.range(tf.size(segment)) - tf.gather(starts, sorted_segment)
    keep = (rank < k) & (sorted_segment < num_segments)
    # Static shapes (a portable program has no dynamic ones): every position is scattered, those not kept into an
    # extra row and column that are cut off.
    where = tf.stack([tf.where(keep, sorted_segment, num_segments), tf.where(keep, rank, k)], -1)
    return tf.tensor_scatter_nd_update(-tf.ones([num_segments + 1, k + 1], tf.int32), where, order)[:-1, :-1]


def teflow_cluster_term(c: _Clouds, v, min_points: int):
    """[B] TeFlow's cluster term (module docstring): per cluster of more than `TEFLOW_TOP_K` points, candidates are,
    from each other sweep, the displacements per sweep of the `TEFLOW_TOP_K` cluster points farthest from it (to their
    nearest point there, over its offset), voting with TEFLOW_TIME_DECAY^|o| (1 + normalised distance), and the
    cluster's mean v, voting with TEFLOW_NETWORK_WEIGHT (1 + its normalised norm); the candidate whose inliers (cosine
    above TEFLOW_COS_THRESHOLD) weigh most wins, the target is its inliers' weighted mean. The sample's term: the mean
    squared error per coordinate over the clusters' points plus the mean over its clusters of their mean |v - target|.
    """
    b, n = tf.shape(c.p0)[0], tf.shape(c.p0)[1]
    segment, num = _segments(c, c.dynamic0, min_points)
    flat_segment = tf.reshape(segment, [-1])
    ones = tf.ones_like(flat_segment, tf.float32)
    size = tf.math.unsorted_segment_sum(ones, flat_segment, num + 1)[:-1]
    flat_v = tf.reshape(v, [-1, 3])
    mean_v = tf.math.unsorted_segment_sum(flat_v, flat_segment, num + 1)[:-1] / tf.maximum(size, 1.0)[:, None]
    flat_p0 = tf.reshape(c.p0, [-1, 3])
    candidates, distances, votes, usable = [], [], [], []
    for xyz, valid, _, offset in c.others:
        matched = _gather(xyz, nearest_indices(c.p0, c.valid0, xyz, valid))
        sq = tf.reshape(tf.reduce_sum(tf.square(c.p0 - matched), -1), [-1])
        top = _top_k_per_segment(tf.where(flat_segment < num, sq, -1.0), flat_segment, num, TEFLOW_TOP_K)
        safe = tf.maximum(top, 0)
        moved = tf.stop_gradient(tf.gather(tf.reshape(matched, [-1, 3]), safe) - tf.gather(flat_p0, safe))
        candidates.append(moved / float(offset))  # [S,K,3]
        distances.append(tf.gather(sq, safe))
        votes.append(tf.fill(tf.shape(top), TEFLOW_TIME_DECAY ** abs(offset)))
        has_points = tf.repeat(tf.reduce_any(valid, -1), num // b)[:, None]
        usable.append((top >= 0) & has_points)
    net_norm = tf.sqrt(tf.reduce_sum(tf.square(mean_v), -1) + 1e-12)
    cand = tf.concat(candidates + [mean_v[:, None]], 1)  # [S,C,3]
    dist = tf.concat(distances + [net_norm[:, None]], 1)  # [S,C]
    use = tf.concat(usable + [tf.ones_like(net_norm[:, None], tf.bool)], 1)
    lo = tf.reduce_min(tf.where(use, dist, _FAR), 1, keepdims=True)
    hi = tf.reduce_max(tf.where(use, dist, -_FAR), 1, keepdims=True)
    normalised = (dist - lo) / (hi - lo + 1e-6)
    weight = tf.concat(votes + [tf.fill(tf.shape(net_norm[:, None]), TEFLOW_NETWORK_WEIGHT)], 1) * (1.0 + normalised)
    weight = tf.where(use, weight, 0.0)
    norms = tf.sqrt(tf.reduce_sum(tf.square(cand), -1))
    cosine = tf.matmul(cand, cand, transpose_b=True) / tf.maximum(norms[:, :, None] * norms[:, None, :], 1e-8)
    inlier = (cosine > TEFLOW_COS_THRESHOLD) & use[:, :, None] & use[:, None, :]
    best = tf.argmax(tf.reduce_sum(tf.cast(inlier, tf.float32) * weight[:, None, :], -1), -1, output_type=tf.int32)
    chosen = tf.cast(tf.gather(inlier, best, batch_dims=1), tf.float32) * weight  # [S,C]
    denominator = tf.reduce_sum(chosen, -1)
    target = tf.where((denominator > 1e-6)[:, None],
                      tf.reduce_sum(chosen[..., None] * cand, 1) / tf.maximum(denominator, 1e-6)[:, None],
                      tf.gather(cand, best, batch_dims=1))
    counted_cluster = (size > TEFLOW_TOP_K) & tf.reduce_any(tf.concat(usable, 1), 1)  # [S]
    point_cluster = tf.minimum(flat_segment, num - 1)
    counted = (flat_segment < num) & tf.gather(counted_cluster, point_cluster)
    diff = flat_v - tf.gather(target, point_cluster)
    sq_error = tf.reshape(tf.reduce_sum(tf.square(diff), -1), [b, n])
    error = tf.sqrt(tf.reduce_sum(tf.square(diff), -1) + 1e-12)
    counted_points = tf.reshape(counted, [b, n])
    point_term = _masked_mean(sq_error, counted_points) / 3.0
    cluster_mean = tf.math.unsorted_segment_sum(tf.where(counted, error, 0.0), flat_segment, num + 1)[:-1] / \
        tf.maximum(size, 1.0)
    per_sample = tf.reshape(counted_cluster, [b, -1])
    cluster_term = _masked_mean(tf.reshape(cluster_mean, [b, -1]), per_sample)
    return point_term + cluster_term


def per_sample_self_supervised_loss(batch, outputs, selfsup, partner: str | None, temporal: bool):
    """[B] SeFlow's loss (`temporal` False: the pair) or TeFlow's (True: every sweep of the batch), each term weighted
    by `selfsup` (`ff3d_tf.config.SelfSupConfig`). `partner`: `data.partner` (None: "previous")."""
    num_clouds = sum(1 for c in schema.sweep_clouds(schema.MAX_NUM_FRAMES) if schema.cloud_keys(c)["xyz"] in batch)
    c = _Clouds(batch, outputs, num_clouds if temporal else 2, partner)
    v = forward_displacement_m(outputs["flow_mps"], partner, selfsup.sweep_period_s)
    chamfer, dynamic = _chamfer_terms(c, v, weighted=temporal)
    cluster = (teflow_cluster_term if temporal else seflow_cluster_term)(c, v, selfsup.cluster_min_points)
    return (selfsup.chamfer_weight * chamfer + selfsup.dynamic_chamfer_weight * dynamic +
            selfsup.static_flow_weight * _static_term(c, v) + selfsup.cluster_weight * cluster)

"""FastFlow3D building blocks (paper Sec. 4 and the architecture table in its appendix).

Notation: B samples, N points per sample (padded), H x W pillars (rows along y, columns along x), C channels.
Every layer takes plain constructor arguments, returns exactly them from `get_config`, and is registered for Keras
serialisation.
"""
from __future__ import annotations

import keras
import tensorflow as tf

_PKG = "ff3d_tf"


def _dense_last_axis(x, kernel):
    """x [..., C] @ kernel [C, U] as one 2-D matmul (no tensordot transposes: inside the point-chunk loop those
    need compile-time shapes under XLA)."""
    kernel = tf.cast(kernel, x.dtype)
    out = tf.matmul(tf.reshape(x, [-1, tf.shape(x)[-1]]), kernel)
    return tf.reshape(out, tf.concat([tf.shape(x)[:-1], tf.shape(kernel)[-1:]], 0))


@keras.saving.register_keras_serializable(package=_PKG)
class Pillarize(keras.layers.Layer):
    """Snap-To-Grid indices and the 8-D point encoding (table rows A/B inputs).

    Args:
      num_pillars_x, num_pillars_y: grid size W, H.
      x_range_m, y_range_m, z_range_m: (min, max) extents in the vehicle frame at t0; points outside (or non-finite,
        or masked) are invalid: they enter no pillar and get no prediction.
    Call:
      points_xyz [B,N,3] metres, point_features [B,N,2] (intensity, elongation), point_mask [B,N] bool.
    Returns:
      encoding [B,N,8] = (cx, cy, cz, dx, dy, dz, l0, l1), zero for invalid points;
      pillar_ids [B,N] int32 flat ids b*H*W + row*W + col, invalid points -> B*H*W (the dummy segment);
      point_valid [B,N] bool.
    """

    def __init__(self, num_pillars_x, num_pillars_y, x_range_m, y_range_m, z_range_m, **kwargs):
        super().__init__(**kwargs)
        self.num_pillars_x, self.num_pillars_y = int(num_pillars_x), int(num_pillars_y)
        self.x_range_m, self.y_range_m, self.z_range_m = tuple(x_range_m), tuple(y_range_m), tuple(z_range_m)
        self._size_x = (self.x_range_m[1] - self.x_range_m[0]) / self.num_pillars_x
        self._size_y = (self.y_range_m[1] - self.y_range_m[0]) / self.num_pillars_y

    def call(self, points_xyz, point_features, point_mask):
        x, y, z = points_xyz[..., 0], points_xyz[..., 1], points_xyz[..., 2]
        # Indices are always computed as (x - min) * (1 / size): graph mode rewrites divisions into this form, so
        # doing it explicitly keeps eager, graph and XLA on the same pillar for every point.
        col_f = tf.floor((x - self.x_range_m[0]) * (1.0 / self._size_x))
        row_f = tf.floor((y - self.y_range_m[0]) * (1.0 / self._size_y))
        finite = tf.reduce_all(tf.math.is_finite(points_xyz), -1) & tf.reduce_all(
            tf.math.is_finite(point_features), -1)
        valid = (point_mask & finite & (col_f >= 0) & (col_f < self.num_pillars_x) & (row_f >= 0) &
                 (row_f < self.num_pillars_y) & (z >= self.z_range_m[0]) & (z <= self.z_range_m[1]))
        col = tf.cast(tf.where(valid, col_f, 0.0), tf.int32)
        row = tf.cast(tf.where(valid, row_f, 0.0), tf.int32)
        cx = self.x_range_m[0] + (tf.cast(col, points_xyz.dtype) + 0.5) * self._size_x
        cy = self.y_range_m[0] + (tf.cast(row, points_xyz.dtype) + 0.5) * self._size_y
        cz = tf.fill(tf.shape(z), tf.constant(0.5 * (self.z_range_m[0] + self.z_range_m[1]), points_xyz.dtype))
        encoding = tf.concat([tf.stack([cx, cy, cz, x - cx, y - cy, z - cz], -1), point_features], -1)
        encoding = tf.where(valid[..., None], encoding, tf.zeros_like(encoding))
        batch = tf.shape(points_xyz)[0]
        cells = self.num_pillars_x * self.num_pillars_y
        sample = tf.range(batch, dtype=tf.int32)[:, None]
        pillar_ids = tf.where(valid, sample * cells + row * self.num_pillars_x + col, batch * cells)
        return encoding, pillar_ids, valid

    def get_config(self):
        return {**super().get_config(), "num_pillars_x": self.num_pillars_x, "num_pillars_y": self.num_pillars_y,
                "x_range_m": self.x_range_m, "y_range_m": self.y_range_m, "z_range_m": self.z_range_m}


@keras.saving.register_keras_serializable(package=_PKG)
class MaskedBatchNorm(keras.layers.Layer):
    """Batch normalisation over the valid points only (padding and invalid points do not move the statistics).

    Four values per channel, as the table counts them: gamma, beta (trainable), moving mean, moving variance.
    Call with one tensor and mask, or with lists of them (e.g. the two clouds): the statistics are then computed
    over all of them together and a list is returned.
    """

    def __init__(self, momentum=0.99, epsilon=1e-3, **kwargs):
        super().__init__(**kwargs)
        self.momentum, self.epsilon = float(momentum), float(epsilon)

    def build(self, input_shape):
        if isinstance(input_shape, (list, tuple)) and isinstance(input_shape[0], (list, tuple)):
            input_shape = input_shape[0]  # called with a list of clouds
        c = int(input_shape[-1])
        self.gamma = self.add_weight(name="gamma", shape=(c,), initializer="ones")
        self.beta = self.add_weight(name="beta", shape=(c,), initializer="zeros")
        self.moving_mean = self.add_weight(name="moving_mean", shape=(c,), initializer="zeros", trainable=False)
        self.moving_variance = self.add_weight(name="moving_variance", shape=(c,), initializer="ones",
                                               trainable=False)

    def call(self, inputs, mask, training=False):
        single = not isinstance(inputs, (list, tuple))
        inputs, mask = ([inputs], [mask]) if single else (list(inputs), list(mask))
        dtype = inputs[0].dtype
        if training:
            ws = [tf.cast(m, dtype)[..., None] for m in mask]
            axes = list(range(len(inputs[0].shape) - 1))
            count = tf.maximum(tf.add_n([tf.reduce_sum(w) for w in ws]), 1.0)
            mean = tf.add_n([tf.reduce_sum(x * w, axes) for x, w in zip(inputs, ws)]) / count
            var = tf.add_n([tf.reduce_sum(tf.square(x - mean) * w, axes) for x, w in zip(inputs, ws)]) / count
            self.moving_mean.assign(self.moving_mean * self.momentum + tf.cast(mean, self.moving_mean.dtype) *
                                    (1.0 - self.momentum))
            self.moving_variance.assign(self.moving_variance * self.momentum +
                                        tf.cast(var, self.moving_variance.dtype) * (1.0 - self.momentum))
        else:
            mean = tf.cast(self.moving_mean, dtype)
            var = tf.cast(self.moving_variance, dtype)
        scale = tf.cast(self.gamma, dtype) * tf.math.rsqrt(var + self.epsilon)
        out = [(x - mean) * scale + tf.cast(self.beta, dtype) for x in inputs]
        return out[0] if single else out

    def get_config(self):
        return {**super().get_config(), "momentum": self.momentum, "epsilon": self.epsilon}


@keras.saving.register_keras_serializable(package=_PKG)
class PointEncoder(keras.layers.Layer):
    """Table rows A and B: the per-point MLP, BN(8-D encoding) -> Linear(8 -> C, no bias) -> ReLU, and Snap-To-Grid
    (each pillar sums the features of its points).

    Reading of row A's 544 parameters: 8 x 64 kernel (no bias, BN follows the input) + 4 x 8 BN values = 544. The
    BN normalises the 8-D encoding, whose channels differ in scale by two orders of magnitude (pillar centres up to
    85 m, offsets < 0.2 m, intensity ~1); a bias would be redundant with BN's beta pushed through the kernel.

    Args:
      units: C, the point feature width.
      num_pillars_x, num_pillars_y: grid W, H of row B's output.
      chunk_size: points (over the flattened batch) encoded and scattered at a time for clouds whose per-point
        features are not kept: memory for one [chunk, C] feature block at any cloud size.
    Call:
      encodings [B,N,8] (`Pillarize`), point_valid [B,N] bool, pillar_ids [B,N] int32 (dummy id B*H*W for invalid
        points); or lists of them, one per cloud: the BN statistics are then joint over all clouds (both frames
        share row A).
      keep_point_features: bool, or one per cloud: also return that cloud's per-point features (row X's input);
        the other clouds are encoded and scattered chunk by chunk without keeping them.
    Returns:
      (bev_features [B,H,W,C], point_features [B,N,C] or None), or (list, list) when called with lists.
    """

    def __init__(self, units=64, num_pillars_x=512, num_pillars_y=512, chunk_size=1 << 18, **kwargs):
        super().__init__(**kwargs)
        self.units = int(units)
        self.num_pillars_x, self.num_pillars_y = int(num_pillars_x), int(num_pillars_y)
        self.chunk_size = int(chunk_size)
        self.norm = MaskedBatchNorm(name="bn")
        self.dense = keras.layers.Dense(self.units, use_bias=False, kernel_initializer="glorot_uniform",
                                        name="linear")

    def build(self, input_shape):
        if isinstance(input_shape, (list, tuple)) and isinstance(input_shape[0], (list, tuple)):
            input_shape = input_shape[0]
        self.norm.build(input_shape)
        self.dense.build(input_shape)

    def call(self, encodings, point_valid, pillar_ids, keep_point_features=False, training=False):
        single = not isinstance(encodings, (list, tuple))
        if single:
            encodings, point_valid, pillar_ids = [encodings], [point_valid], [pillar_ids]
        keep = ([bool(keep_point_features)] * len(encodings) if isinstance(keep_point_features, bool)
                else [bool(k) for k in keep_point_features])
        normed = self.norm(list(encodings), list(point_valid), training=training)  # joint statistics
        grids, features = [], []
        for x, valid, ids, k in zip(normed, point_valid, pillar_ids, keep):
            grid, feat = self._encode_and_scatter(x, valid, ids, k)
            grids.append(grid)
            features.append(feat)
        return (grids[0], features[0]) if single else (grids, features)

    def _features(self, normed, point_valid):
        """Linear + ReLU of normalised encodings [..,8] -> [..,C]; zero for invalid points."""
        h = tf.nn.relu(_dense_last_axis(normed, self.dense.kernel))
        return tf.where(point_valid[..., None], h, tf.zeros_like(h))

    def _encode_and_scatter(self, normed, point_valid, pillar_ids, keep):
        """One cloud: grid [B,H,W,C] (row B, segment sum over flat pillar ids, dummy segment last) and the features
        [B,N,C] when `keep`."""
        batch = tf.shape(normed)[0]
        num_segments = batch * self.num_pillars_x * self.num_pillars_y + 1
        if keep:
            features = self._features(normed, point_valid)  # [B,N,C]
            grid = tf.math.unsorted_segment_sum(features, pillar_ids, num_segments)
        else:
            features, grid = None, self._chunked_scatter(normed, point_valid, pillar_ids, num_segments)
        return tf.reshape(grid[:-1], [batch, self.num_pillars_y, self.num_pillars_x, self.units]), features

    def _chunked_scatter(self, normed, point_valid, pillar_ids, num_segments):
        """Segment sums [num_segments, C] of the features, `chunk_size` points at a time. The B*N points are
        flattened (ids are global over the batch), padded to whole chunks and taken chunk by chunk: no transposes,
        and no [B*N, C] feature array."""
        batch, n = tf.shape(normed)[0], tf.shape(normed)[1]
        total = batch * n
        if None not in normed.shape[:2]:
            total_static = normed.shape[0] * normed.shape[1]
            chunk = max(min(self.chunk_size, total_static), 1)
            num_chunks = max(-(-total_static // chunk), 1)
        else:
            chunk = tf.maximum(tf.minimum(self.chunk_size, total), 1)
            num_chunks = tf.maximum((total + chunk - 1) // chunk, 1)
        pad = num_chunks * chunk - total

        def chunks(t, fill):  # [B,N,...] -> [K,chunk,...]
            flat = tf.reshape(t, tf.concat([[total], tf.shape(t)[2:]], 0))
            flat = tf.pad(flat, [[0, pad]] + [[0, 0]] * (len(t.shape) - 2), constant_values=fill)
            return tf.reshape(flat, tf.concat([[num_chunks, chunk], tf.shape(t)[2:]], 0))

        normed_c = chunks(normed, 0.0)  # [K,chunk,8]
        valid_c = chunks(point_valid, False)
        ids_c = chunks(pillar_ids, num_segments - 1)

        # A gradient of its own (recomputing each chunk's features) instead of the loop's automatic one: the
        # automatic gradient keeps every chunk's intermediates in TensorLists, which may not leave an XLA program
        # (the point stage's forward and backward are separate programs in compile mode "hybrid").
        @tf.custom_gradient
        def scatter(normed_c, kernel):
            def forward(i, grid):
                feat = tf.where(valid_c[i][:, None], tf.nn.relu(tf.matmul(normed_c[i], kernel)), 0.0)  # [chunk,C]
                return [i + 1, grid + tf.math.unsorted_segment_sum(feat, ids_c[i], num_segments)]

            grid = tf.zeros([num_segments, self.units], normed_c.dtype)
            _, grid = tf.while_loop(lambda i, _: i < num_chunks, forward, [tf.constant(0), grid],
                                    maximum_iterations=num_chunks)

            def grad(d_grid):  # [num_segments, C] -> d normed_c [K,chunk,8], d kernel [8,C]
                def backward(i, d_normed, d_kernel):
                    pre = tf.matmul(normed_c[i], kernel)
                    d_pre = tf.where(valid_c[i][:, None] & (pre > 0), tf.gather(d_grid, ids_c[i]), 0.0)
                    d_kernel = d_kernel + tf.matmul(normed_c[i], d_pre, transpose_a=True)
                    d_chunk = tf.matmul(d_pre, kernel, transpose_b=True)
                    return [i + 1, tf.tensor_scatter_nd_update(d_normed, [[i]], d_chunk[None]), d_kernel]

                _, d_normed, d_kernel = tf.while_loop(
                    lambda i, *_: i < num_chunks, backward,
                    [tf.constant(0), tf.zeros_like(normed_c), tf.zeros_like(kernel)], maximum_iterations=num_chunks)
                return d_normed, d_kernel

            return grid, grad

        return scatter(normed_c, tf.cast(self.dense.kernel, normed.dtype))

    def get_config(self):
        return {**super().get_config(), "units": self.units, "num_pillars_x": self.num_pillars_x,
                "num_pillars_y": self.num_pillars_y, "chunk_size": self.chunk_size}


@keras.saving.register_keras_serializable(package=_PKG)
class ConvBlock(keras.layers.Layer):
    """Table rows C-R: 3x3 convolution (no bias), BatchNorm, ReLU."""

    def __init__(self, filters, strides=1, **kwargs):
        super().__init__(**kwargs)
        self.filters, self.strides = int(filters), int(strides)
        self.conv = keras.layers.Conv2D(self.filters, 3, strides=self.strides, padding="same", use_bias=False,
                                        kernel_initializer="glorot_uniform", name="conv")
        self.bn = keras.layers.BatchNormalization(name="bn")

    def build(self, input_shape):
        self.conv.build(input_shape)
        self.bn.build(self.conv.compute_output_shape(input_shape))

    def call(self, x, training=False):
        return tf.nn.relu(self.bn(self.conv(x), training=training))

    def compute_output_shape(self, input_shape):
        return self.conv.compute_output_shape(input_shape)

    def get_config(self):
        return {**super().get_config(), "filters": self.filters, "strides": self.strides}


@keras.saving.register_keras_serializable(package=_PKG)
class UpsampleSkip(keras.layers.Layer):
    """Table rows S, T, U, Upsample-Skip(alpha, beta, d, d_b); linear throughout (no BN, no nonlinearity).

    U1 = 1x1 conv(alpha) -> d_b; U2 = bilinear x2 of U1; U3 = 1x1 conv(beta) -> d_b; U4 = concat(U2, U3);
    U5 = 3x3 conv(U4) -> d; U6 = 3x3 conv(U5) -> d. All convolutions without bias.
    """

    def __init__(self, depth, bottleneck_depth, **kwargs):
        super().__init__(**kwargs)
        self.depth, self.bottleneck_depth = int(depth), int(bottleneck_depth)
        conv = dict(use_bias=False, padding="same", kernel_initializer="glorot_uniform")
        self.u1 = keras.layers.Conv2D(self.bottleneck_depth, 1, name="U1", **conv)
        # U2 in float32 under mixed precision: TensorFlow's XLA lowering of the bilinear resize's gradient
        # (ResizeBilinearGrad) returns float32 for bfloat16 inputs, which XLA rejects in a bfloat16 training step.
        self.u2 = keras.layers.UpSampling2D(2, interpolation="bilinear", name="U2", dtype="float32")
        self.u3 = keras.layers.Conv2D(self.bottleneck_depth, 1, name="U3", **conv)
        self.u5 = keras.layers.Conv2D(self.depth, 3, name="U5", **conv)
        self.u6 = keras.layers.Conv2D(self.depth, 3, name="U6", **conv)

    def build(self, input_shape):
        alpha_shape, beta_shape = input_shape
        self.u1.build(alpha_shape)
        self.u3.build(beta_shape)
        self.u5.build(tuple(beta_shape[:-1]) + (2 * self.bottleneck_depth,))
        self.u6.build(tuple(beta_shape[:-1]) + (self.depth,))

    def call(self, inputs):
        alpha, beta = inputs
        u1 = self.u1(alpha)
        u4 = tf.concat([tf.cast(self.u2(tf.cast(u1, tf.float32)), u1.dtype), self.u3(beta)], -1)
        return self.u6(self.u5(u4))

    def get_config(self):
        return {**super().get_config(), "depth": self.depth, "bottleneck_depth": self.bottleneck_depth}


@keras.saving.register_keras_serializable(package=_PKG)
class UngridHead(keras.layers.Layer):
    """Table rows W, X, Y: Ungrid (each t0 point takes its pillar's flow embedding), concatenation with the point
    feature, and the linear layer Y.

    Reading of row Y's 4,384 parameters: Linear(136 -> 32) with bias = 136 x 32 + 32, whose input is X (W's 64-d
    cell embedding + A's 64-d point feature = the table's 128) plus the point's 8-D encoding (raw geometry beside the
    learned features); no BN, no nonlinearity, as the table says. This is the reading that, with row A's, reproduces
    the 5,233,571 total.

    concat([w, a, e]) @ K = w @ K_w + a @ K_a + e @ K_e, so the grid part is projected to 32 channels on the grid first
    and 32 (not 64) values are gathered per point: the same function with far less per-point memory traffic.

    Call: [bev [B,H,W,Cg], point_features [B,N,Cp] (row A), encoding [B,N,8] (`Pillarize`), pillar_ids [B,N]].
    Returns: [B,N,U]; rows of invalid points are arbitrary (the caller masks them).
    """

    def __init__(self, units=32, **kwargs):
        super().__init__(**kwargs)
        self.units = int(units)

    def build(self, input_shape):
        """input_shape: (grid [.., Cg], point features [.., Cp], encoding [.., 8][, pillar ids])."""
        grid_shape, point_shape, encoding_shape = input_shape[0], input_shape[1], input_shape[2]
        self.grid_channels = int(grid_shape[-1])
        self.point_channels = int(point_shape[-1])
        fan_in = self.grid_channels + self.point_channels + int(encoding_shape[-1])
        self.kernel = self.add_weight(name="kernel", shape=(fan_in, self.units), initializer="glorot_uniform")
        self.bias = self.add_weight(name="bias", shape=(self.units,), initializer="zeros")

    def call(self, inputs):
        """inputs: bev [B,H,W,Cg], point_features [B,N,Cp], encoding [B,N,8], pillar_ids [B,N] -> [B,N,U]."""
        bev, point_features, encoding, pillar_ids = inputs
        kernel = tf.cast(self.kernel, bev.dtype)
        k_grid = kernel[: self.grid_channels]
        k_point = kernel[self.grid_channels: self.grid_channels + self.point_channels]
        k_enc = kernel[self.grid_channels + self.point_channels:]
        point_features = tf.cast(point_features, bev.dtype)
        point_term = (_dense_last_axis(point_features, k_point) + _dense_last_axis(tf.cast(encoding, bev.dtype), k_enc)
                      + tf.cast(self.bias, bev.dtype))  # a @ K_a + e @ K_e + bias, [B,N,U]
        projected = tf.reshape(tf.einsum("bhwc,cu->bhwu", bev, k_grid), [-1, self.units])  # [B*H*W, U]
        cells = tf.shape(projected)[0]
        safe_ids = tf.minimum(pillar_ids, cells - 1)  # dummy ids gather any cell; masked by the caller
        return tf.gather(projected, safe_ids) + point_term  # [B,N,U]

    def get_config(self):
        return {**super().get_config(), "units": self.units}

"""FastFlow3D building blocks (paper Sec. 4 and the architecture table in its appendix).

Notation: B samples, N points per sample (padded), H x W pillars (rows along y, columns along x), C channels.
Every layer takes plain constructor arguments, returns exactly them from `get_config`, and is registered for Keras
serialisation.
"""
from __future__ import annotations

import keras
import tensorflow as tf

from ff3d_tf import internals
from ff3d_tf.model import ops

_PKG = "ff3d_tf"


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
        pillar_ids, valid = self.cells(points_xyz, point_features, point_mask)
        return self.encode(self.point_rows(points_xyz, point_features), valid), pillar_ids, valid

    def _columns_rows(self, x, y):
        """Float column and row of each point's pillar (not yet checked against the grid). Always (v - min) *
        (1 / size): graph mode rewrites divisions into this form, so doing it explicitly keeps eager, graph and XLA on
        the same pillar for every point; and `cells` and `encode` compute it the same way."""
        return (tf.floor((x - self.x_range_m[0]) * (1.0 / self._size_x)),
                tf.floor((y - self.y_range_m[0]) * (1.0 / self._size_y)))

    def cells(self, points_xyz, point_features, point_mask):
        """(pillar_ids [B,N] int32, point_valid [B,N] bool) as `call` returns them, without the encoding."""
        z = points_xyz[..., 2]
        col_f, row_f = self._columns_rows(points_xyz[..., 0], points_xyz[..., 1])
        finite = tf.reduce_all(tf.math.is_finite(points_xyz), -1) & tf.reduce_all(
            tf.math.is_finite(point_features), -1)
        valid = (point_mask & finite & (col_f >= 0) & (col_f < self.num_pillars_x) & (row_f >= 0) &
                 (row_f < self.num_pillars_y) & (z >= self.z_range_m[0]) & (z <= self.z_range_m[1]))
        col = tf.cast(tf.where(valid, col_f, 0.0), tf.int32)
        row = tf.cast(tf.where(valid, row_f, 0.0), tf.int32)
        batch = tf.shape(points_xyz)[0]
        cells = self.num_pillars_x * self.num_pillars_y
        sample = tf.range(batch, dtype=tf.int32)[:, None]
        pillar_ids = tf.where(valid, sample * cells + row * self.num_pillars_x + col, batch * cells)
        return pillar_ids, valid

    @staticmethod
    def point_rows(points_xyz, point_features):
        """[..., 5] = (x, y, z, l0, l1): what `encode` takes."""
        return tf.concat([points_xyz, tf.cast(point_features, points_xyz.dtype)], -1)

    def encode(self, point_rows, point_valid):
        """The 8-D encoding [..., 8] of points given as `point_rows` [..., 5] (any leading shape: a cloud, or a chunk
        of the point encoder's loop, which computes it there instead of reading an [N, 8] array), zero where
        `point_valid` [...] is False."""
        x, y, z = point_rows[..., 0], point_rows[..., 1], point_rows[..., 2]
        col_f, row_f = self._columns_rows(x, y)
        cx = self.x_range_m[0] + (col_f + 0.5) * self._size_x
        cy = self.y_range_m[0] + (row_f + 0.5) * self._size_y
        cz = tf.fill(tf.shape(z), tf.constant(0.5 * (self.z_range_m[0] + self.z_range_m[1]), point_rows.dtype))
        channels = [cx, cy, cz, x - cx, y - cy, z - cz, point_rows[..., 3], point_rows[..., 4]]
        # Masked channel by channel, then stacked: XLA builds the encoding in one pass.
        return tf.stack([tf.where(point_valid, c, tf.zeros_like(c)) for c in channels], -1)

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
        inputs = [inputs] if single else list(inputs)
        mean, scale, beta = self.normalizer(inputs, [mask] if single else list(mask), training)
        out = [(x - mean) * scale + beta for x in inputs]
        return out[0] if single else out

    def normalizer(self, inputs, mask, training=False):
        """(mean, scale, beta) [C] each in the inputs' dtype, BN(x) = (x - mean) * scale + beta: the statistics of the
        valid points of all `inputs` (a list, with its masks) when training (the moving ones are updated), else the
        moving ones. For callers that normalise chunk by chunk."""
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
        return mean, scale, tf.cast(self.beta, dtype)

    def get_config(self):
        return {**super().get_config(), "momentum": self.momentum, "epsilon": self.epsilon}


@keras.saving.register_keras_serializable(package=_PKG)
class PointEncoder(keras.layers.Layer):
    """Table rows A and B: the per-point MLP, BN(8-D encoding) -> Linear(8 -> C, no bias) -> ReLU, and Snap-To-Grid
    (each pillar sums the features of its points).

    Reading of row A's 544 parameters: 8 x 64 kernel (no bias, BN follows the input) + 4 x 8 BN values = 544. The
    BN normalises the 8-D encoding, whose channels differ in scale by two orders of magnitude (pillar centres up to
    85 m, offsets < 0.2 m, intensity ~1); a bias would be redundant with BN's beta pushed through the kernel.

    The points are normalised, encoded and scattered `chunk_size` at a time (`ops.chunked_segment_sum`): no [N, C]
    feature array exists at any cloud size, and with `encode` no [N, 8] encoding either (the model passes the points'
    5 input values and `Pillarize.encode`). The head takes a point's feature (and encoding) only through a linear
    map, so the encoder applies that map chunk by chunk (`point_projections`) instead of keeping the features.

    Args:
      units: C, the point feature width.
      num_pillars_x, num_pillars_y: grid W, H of row B's output.
      chunk_size: points (over the flattened batch) encoded and scattered at a time.
    Call:
      points [B,N,D]: the 8-D encodings (`Pillarize.call`), or with `encode` the rows it encodes
        (`Pillarize.point_rows`); point_valid [B,N] bool, pillar_ids [B,N] int32 (ids of invalid points are
        ignored); or lists of them, one per cloud: the BN statistics are then joint over all clouds (both frames
        share row A).
      encode: None, or a function (rows [..., D], valid [...]) -> encodings [..., 8] (`Pillarize.encode`) that the
        loop applies to each chunk: no [N, 8] encoding is stored, only the statistics of training read it whole.
      point_projections: None, a kernel [C + 8, U], or (with lists) one of them (or None) per cloud: also return
        concat(point feature, encoding) @ kernel for that cloud's points, [B,N,U].
    Returns:
      (bev_features [B,H,W,C] float32 (pillar sums, also under mixed precision), projected point features [B,N,U]
        or None), or (list, list) when called with lists.
    """

    def __init__(self, units=64, num_pillars_x=512, num_pillars_y=512, chunk_size=ops.POINT_CHUNK, **kwargs):
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

    def call(self, points, point_valid, pillar_ids, point_projections=None, encode=None, training=False,
             stage=None):
        """`stage`: None (everything traced inline, in the caller's graph or XLA program), or a function that makes
        a function its own program (`ff3d_tf.model.compile.xla_function`): the statistics of training, then each
        cloud's encoding and scatter, are then separate programs. The clouds' programs depend on nothing of each
        other, so TensorFlow's executor runs them at the same time on its inter-op threads (compile mode hybrid on a
        CPU, where XLA runs a scatter on one thread)."""
        single = not isinstance(points, (list, tuple))
        if single:
            points, point_valid, pillar_ids = [points], [point_valid], [pillar_ids]
            point_projections = [point_projections]
        elif point_projections is None:
            point_projections = [None] * len(points)
        points = [tf.cast(p, self.compute_dtype) for p in points]
        encode = encode or (lambda encoding, valid: encoding)
        # Joint statistics of the whole clouds' encodings in training (inference takes the moving ones, and the
        # points only for their dtype); the normalisation itself is applied chunk by chunk.
        if training:
            def statistics(points, point_valid):
                return self.norm.normalizer([encode(p, v) for p, v in zip(points, point_valid)], list(point_valid),
                                            training=True)
            normalizer = (stage(statistics) if stage else statistics)(points, list(point_valid))
        else:
            normalizer = self.norm.normalizer(points, list(point_valid), training=False)
        grids, projected = [], []
        for cloud, valid, ids, projection in zip(points, point_valid, pillar_ids, point_projections):
            def encode_cloud(cloud, valid, ids, normalizer, projection=projection):
                return self._encode_and_scatter(cloud, valid, ids, normalizer, projection, encode)
            grid, rows = (stage(encode_cloud) if stage else encode_cloud)(cloud, valid, ids, list(normalizer))
            grids.append(grid)
            projected.append(rows)
        return (grids[0], projected[0]) if single else (grids, projected)

    def point_features(self, encodings, point_valid, training=False):
        """Row A as the table lists it, for the table forward: the 8-D encodings [B,N,8] of the clouds (a list, with
        their validity [B,N]; one set of BN statistics over all of them) -> their point features [B,N,C] (float32,
        0 where invalid). `call` computes the same chunk by chunk, scattered into the grid as it goes."""
        normalized = self.norm(list(encodings), list(point_valid), training=training)
        features = [tf.nn.relu(self.dense(x)) for x in normalized]
        return [tf.where(v[..., None], f, tf.zeros_like(f)) for f, v in zip(features, point_valid)]

    def _encode_and_scatter(self, points, point_valid, pillar_ids, normalizer, projection, encode):
        """One cloud: grid [B,H,W,C] (row B: segment sums over flat pillar ids) and, with a projection kernel
        [C + 8, U], the projected features [B,N,U]."""
        batch, n, dims = tf.shape(points)[0], tf.shape(points)[1], points.shape[-1]
        cells = batch * self.num_pillars_y * self.num_pillars_x

        def encode_chunk(points, valid, weights):  # a chunk: points [P,D], valid [P]
            encoding = encode(points, valid)  # [P,8]
            mean, scale, beta, kernel = weights[:4]
            features = tf.nn.relu(ops.narrow_matmul((encoding - mean) * scale + beta, kernel))  # [P,C]
            features = tf.where(valid[:, None], features, tf.zeros_like(features))
            # Pillar sums in float32 also under mixed precision: a pillar holds up to hundreds of points, whose sum
            # bfloat16 (8-bit mantissa) would round; and GPUs add float32 atomically, bfloat16 by compare-and-swap.
            pillar_values = tf.cast(features, tf.float32)
            if projection is None:
                return pillar_values, None
            # The encoding's share as a sum of 8 products, not a matrix product: XLA fuses it with the
            # encoding's computation instead of materialising a copy of the encoding for a dot.
            by_encoding = tf.reduce_sum(encoding[:, :, None] * weights[4][self.units:], 1)
            return pillar_values, tf.matmul(features, weights[4][:self.units]) + by_encoding

        weights = [*normalizer, self.dense.kernel] + ([] if projection is None else [projection])
        grid, rows = ops.chunked_segment_sum(
            encode_chunk, tf.reshape(points, [-1, dims]), tf.reshape(point_valid, [-1]),
            [tf.cast(w, points.dtype) for w in weights], tf.reshape(tf.where(point_valid, pillar_ids, -1), [-1]),
            cells, self.chunk_size)
        grid = tf.reshape(grid, [batch, self.num_pillars_y, self.num_pillars_x, self.units])
        return grid, (None if rows is None else tf.reshape(rows, [batch, n, -1]))

    def get_config(self):
        return {**super().get_config(), "units": self.units, "num_pillars_x": self.num_pillars_x,
                "num_pillars_y": self.num_pillars_y, "chunk_size": self.chunk_size}


@keras.saving.register_keras_serializable(package=_PKG)
class Conv2D(keras.layers.Conv2D):
    """Keras's Conv2D (the same weights, names and config) with two ways of computing it that XLA's CPU backend runs
    faster, each equal to the plain convolution up to float rounding, chosen by the execution plan
    (`ff3d_tf.model.plan`; `FastFlow3D` sets them on its layers when it is built; both off by default):

      - `matmul_1x1`: a 1x1 kernel with stride 1 is a matrix product over the last axis (`ops.dense_last_axis`),
        which XLA's CPU backend computes faster than the same product written as a convolution (rows U1, U3);
      - `stride2_phase_gradients`: a 3x3 stride-2 kernel computes its gradients as stride-1 convolutions
        (`ops.conv2d_stride2`; rows C, G, M).
    """

    matmul_1x1 = False
    stride2_phase_gradients = False

    def convolution_op(self, inputs, kernel):
        one = (1, 1)
        if (self.matmul_1x1 and tuple(kernel.shape[:2]) == one and tuple(self.strides) == one and
                tuple(self.dilation_rate) == one):
            return ops.dense_last_axis(inputs, kernel[0, 0])
        if self.stride2_phase_gradients and ops.stride2_by_phases_applies(inputs.shape, kernel.shape, self.strides,
                                                                          self.padding):
            return ops.conv2d_stride2(inputs, kernel)
        return super().convolution_op(inputs, kernel)


@keras.saving.register_keras_serializable(package=_PKG)
class ConvBlock(keras.layers.Layer):
    """Table rows C-R: 3x3 convolution (no bias), BatchNorm, ReLU.

    The BatchNorm runs as TensorFlow's fused kernel (FusedBatchNormV3 and its gradient, `internals.fused_batch_norm`)
    on the variables of `self.bn` (a Keras BatchNormalization: gamma, beta, moving mean and variance; checkpoints and
    parameter count unchanged), with Keras's numbers: momentum and epsilon of `self.bn`, statistics in float32 also
    under mixed precision, and a moving variance without Bessel's correction. Keras's own layer is a chain of
    elementwise ops and reductions forward and backward; the fused kernel is one pass each way, oneDNN fuses it with
    the ReLU in training and with the convolution in inference (_FusedConv2D), and XLA compiles it (and its gradient)
    as well.
    """

    def __init__(self, filters, strides=1, **kwargs):
        super().__init__(**kwargs)
        self.filters, self.strides = int(filters), int(strides)
        # Inference only: the BatchNorm folded into the convolution (`_folded`); the execution plan's field, set by
        # `FastFlow3D` when it is built.
        self.fold_batch_norm = False
        self.conv = Conv2D(self.filters, 3, strides=self.strides, padding="same", use_bias=False,
                           kernel_initializer="glorot_uniform", name="conv")
        self.bn = keras.layers.BatchNormalization(name="bn")

    def build(self, input_shape):
        self.conv.build(input_shape)
        self.bn.build(self.conv.compute_output_shape(input_shape))

    def call(self, x, training=False):
        y, statistics = self.forward(x, training)
        if statistics is not None:
            self.update_moving_statistics(*statistics)
        return y

    def forward(self, x, training=False):
        """(the block's output, the batch's (mean, variance) for the moving statistics, or None when they are not
        updated): `call` without the update, so a recomputation of the block (`FastFlow3D.remat_encoder`) assigns
        nothing."""
        bn = self.bn
        gamma, beta = tf.cast(bn.gamma, tf.float32), tf.cast(bn.beta, tf.float32)
        if self.fold_batch_norm and not training:
            return self._folded(x, gamma, beta), None
        y = self.conv(x)
        if training and bn.trainable:
            y, mean, variance = internals.fused_batch_norm(y, gamma, beta, epsilon=bn.epsilon, training=True)
            # The op's batch variance carries Bessel's correction n / (n - 1) (n = B*H*W values per channel; 8e-6 to
            # 1.2e-4 relative at batch 1 on the paper grid); Keras's moving variance is the plain E[(y - mean)^2].
            n = tf.cast(tf.reduce_prod(tf.shape(y)[:-1]), tf.float32)
            return tf.nn.relu(y), (mean, variance * ((n - 1.0) / tf.maximum(n, 1.0)))
        y, _, _ = internals.fused_batch_norm(y, gamma, beta, epsilon=bn.epsilon, training=False,
                                             mean=tf.cast(bn.moving_mean, tf.float32),
                                             variance=tf.cast(bn.moving_variance, tf.float32))
        return tf.nn.relu(y), None

    def _folded(self, x, gamma, beta):
        """The inference block with the BatchNorm folded into the convolution: scale = gamma / sqrt(var + eps)
        multiplies the kernel's output channels (in float32, then cast to the convolution's dtype) and
        beta - mean * scale is the bias, so a compiler fuses convolution, bias and ReLU into one kernel (cuDNN's
        conv-bias-activation) instead of a convolution and a pass over its output. Equal to the unfolded block up to
        rounding."""
        bn = self.bn
        scale = gamma * tf.math.rsqrt(tf.cast(bn.moving_variance, tf.float32) + bn.epsilon)
        bias = beta - tf.cast(bn.moving_mean, tf.float32) * scale
        kernel = tf.cast(tf.cast(self.conv.kernel, tf.float32) * scale, x.dtype)
        y = tf.nn.conv2d(x, kernel, strides=self.strides, padding="SAME")
        return tf.nn.relu(tf.nn.bias_add(y, tf.cast(bias, y.dtype)))

    def update_moving_statistics(self, mean, variance):
        """Keras's moving averages of `forward`'s batch statistics."""
        bn, m = self.bn, self.bn.momentum
        bn.moving_mean.assign(tf.cast(bn.moving_mean, tf.float32) * m + mean * (1.0 - m))
        bn.moving_variance.assign(tf.cast(bn.moving_variance, tf.float32) * m + variance * (1.0 - m))

    def compute_output_shape(self, input_shape):
        return self.conv.compute_output_shape(input_shape)

    def get_config(self):
        return {**super().get_config(), "filters": self.filters, "strides": self.strides}


@keras.saving.register_keras_serializable(package=_PKG)
class BilinearUpsample2x(keras.layers.Layer):
    """Row U2's bilinear x2 upsampling, the values of `keras.layers.UpSampling2D(2, interpolation="bilinear")` as
    `ops.bilinear_upsample_2x` computes them (no temporary beyond the tensors' own size under XLA)."""

    def call(self, x):
        return ops.bilinear_upsample_2x(x)

    def compute_output_shape(self, input_shape):
        b, h, w, c = input_shape
        return (b, None if h is None else 2 * h, None if w is None else 2 * w, c)


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
        self.u1 = Conv2D(self.bottleneck_depth, 1, name="U1", **conv)
        self.u2 = BilinearUpsample2x(name="U2", dtype="float32")  # float32 also under mixed precision
        self.u3 = Conv2D(self.bottleneck_depth, 1, name="U3", **conv)
        self.u5 = Conv2D(self.depth, 3, name="U5", **conv)
        self.u6 = Conv2D(self.depth, 3, name="U6", **conv)

    def build(self, input_shape):
        alpha_shape, beta_shape = input_shape
        self.u1.build(alpha_shape)
        self.u3.build(beta_shape)
        self.u5.build(tuple(beta_shape[:-1]) + (2 * self.bottleneck_depth,))
        self.u6.build(tuple(beta_shape[:-1]) + (self.depth,))

    def call(self, inputs):
        return self.u6(self.u5(self.merged(inputs)))

    def merged(self, inputs, u1=None):
        """U4 (U1-U4 of [alpha, beta]): what U5 convolves. `u1`: U1's output, where the caller has computed it (then
        alpha is not read)."""
        alpha, beta = inputs
        u1 = self.u1(alpha) if u1 is None else u1
        return tf.concat([tf.cast(self.u2(tf.cast(u1, tf.float32)), u1.dtype), self.u3(beta)], -1)

    def into_next(self, inputs, following: "UpsampleSkip", u1=None):
        """`following.u1(self(inputs))`, `following`'s U1 of this block's output, as this block computes it when U1
        is all that reads its output: U6 (3x3) and U1 (1x1) are linear with nothing between them, so they are one
        3x3 convolution to U1's channels, whose kernel is U6's mapped by U1's (`ops.composed_kernel`; a 1x1 kernel
        composes with no change at the border). The same values up to float rounding, for U1's fewer output channels
        instead of U6's. `u1`: this block's own U1 output, as `merged` takes it."""
        kernel = ops.composed_kernel(self.u6.kernel, following.u1.kernel)
        x = self.u5(self.merged(inputs, u1))
        return tf.nn.conv2d(x, tf.cast(kernel, x.dtype), 1, "SAME")

    def get_config(self):
        return {**super().get_config(), "depth": self.depth, "bottleneck_depth": self.bottleneck_depth}


@keras.saving.register_keras_serializable(package=_PKG)
class UngridHead(keras.layers.Layer):
    """Table row Y, the linear layer on row X (row W's cell embedding of each t0 point, concatenated with its point
    feature), with row W's gather (`ungrid`) beside it.

    Reading of row Y's 4,384 parameters: Linear(136 -> 32) with bias = 136 x 32 + 32, whose input is X (W's 64-d
    cell embedding + A's 64-d point feature = the table's 128) plus the point's 8-D encoding (raw geometry beside the
    learned features); no BN, no nonlinearity, as the table says. This is the reading that, with row A's, reproduces
    the 5,233,571 total.

    concat([w, a, e]) @ K = w @ K_w + a @ K_a + e @ K_e (`split_kernel`), and rows Y and Z are linear with nothing
    between them (`composed_with`): the fused forward projects the grid part to 3 values per cell before the gather
    and the point part inside row A's chunk loop, instead of building X.

    Args:
      units: U, row Y's width.
      grid_channels, point_channels: the widths of X's cell embedding (row V's) and point feature (row A's) parts.
    Call: x [B,N,grid_channels + point_channels + 8] (row X) -> [B,N,U].
    """

    def __init__(self, units=32, grid_channels=64, point_channels=64, **kwargs):
        super().__init__(**kwargs)
        self.units, self.grid_channels, self.point_channels = int(units), int(grid_channels), int(point_channels)

    def build(self, input_shape):
        fan_in = self.grid_channels + self.point_channels + 8
        if input_shape[-1] is not None and int(input_shape[-1]) != fan_in:
            raise ValueError(f"UngridHead: row X has {fan_in} channels (cell {self.grid_channels}, point "
                             f"{self.point_channels}, encoding 8), got {input_shape[-1]}")
        self.kernel = self.add_weight(name="kernel", shape=(fan_in, self.units), initializer="glorot_uniform")
        self.bias = self.add_weight(name="bias", shape=(self.units,), initializer="zeros")

    def call(self, x):
        return ops.dense_last_axis(x, tf.cast(self.kernel, x.dtype)) + tf.cast(self.bias, x.dtype)

    def split_kernel(self, kernel):
        """A kernel [Cg + Cp + 8, U'] as the parts that multiply the cell embedding, point feature and encoding."""
        g, p = self.grid_channels, self.point_channels
        return kernel[:g], kernel[g:g + p], kernel[g + p:]

    @staticmethod
    def ungrid(grid, pillar_ids):
        """Row W: grid [B,H,W,U'] -> each point's cell [B,N,U'] (pillar ids flat over the batch; points in no
        pillar take any cell: the caller masks them)."""
        cells = tf.reshape(grid, [-1, grid.shape[-1]])
        return tf.gather(cells, tf.minimum(pillar_ids, tf.shape(cells)[0] - 1))

    def composed_with(self, output_layer):
        """This row followed by the linear `output_layer` (row Z, nothing between them) as one linear map:
        Z(Y(x)) = x @ (K_Y K_Z) + (b_Y K_Z + b_Z). Returns (grid, point feature, encoding) kernel parts [.., 3] and
        the bias [3], in the variables' dtype."""
        kernel = tf.matmul(self.kernel, output_layer.kernel)
        bias = tf.linalg.matvec(output_layer.kernel, self.bias, transpose_a=True) + output_layer.bias
        return (*self.split_kernel(kernel), bias)

    def get_config(self):
        return {**super().get_config(), "units": self.units, "grid_channels": self.grid_channels,
                "point_channels": self.point_channels}

"""FastFlow3D (Jund et al., Sec. 4 and the appendix architecture table) as a Keras 3 model.

Inputs (dict, batched and padded; see `ff3d_tf.schema`):
  points_xyz_t0 [B,N0,3], point_features_t0 [B,N0,2], point_mask_t0 [B,N0] bool,
  points_xyz_tm1_in_t0 [B,N1,3], point_features_tm1 [B,N1,2], point_mask_tm1 [B,N1] bool.
Outputs (dict): flow_mps [B,N0,3] (m/s, vehicle frame at t0; 0 where invalid), point_valid [B,N0] bool.

Both clouds share the point encoder (A) and the convolutional encoder (C-R): the two frames are stacked along the
batch axis and pass through the same layers once. The decoder (S, T, U, V) takes the depth-wise concatenation of the
two encoders' layers (t0 first), and the head (W-Z) regresses flow for the t0 points.
"""
from __future__ import annotations

import string

import keras
import tensorflow as tf

from ff3d_tf.config import ExperimentConfig
from ff3d_tf.model import layers as L

# Points per chunk of the point encoder / scatter loop: bounds the [chunk, 64] feature memory at any cloud size.
POINT_CHUNK = 1 << 18

INPUT_KEYS = ("points_xyz_t0", "point_features_t0", "point_mask_t0", "points_xyz_tm1_in_t0", "point_features_tm1",
              "point_mask_tm1")


@keras.saving.register_keras_serializable(package="ff3d_tf")
class FastFlow3D(keras.Model):
    def __init__(self, num_pillars_x=512, num_pillars_y=512, x_range_m=(-85.0, 85.0), y_range_m=(-85.0, 85.0),
                 z_range_m=(-3.0, 3.0), point_feature_dim=64, encoder_widths=(64, 128, 256), encoder_depths=(4, 6, 6),
                 decoder_dims=((128, 128), (128, 64), (64, 64)), head_hidden_dim=32, zero_init_output=False,
                 **kwargs):
        super().__init__(**kwargs)
        self.num_pillars_x, self.num_pillars_y = int(num_pillars_x), int(num_pillars_y)
        self.x_range_m, self.y_range_m, self.z_range_m = tuple(x_range_m), tuple(y_range_m), tuple(z_range_m)
        self.point_feature_dim = int(point_feature_dim)
        self.encoder_widths = tuple(int(w) for w in encoder_widths)
        self.encoder_depths = tuple(int(d) for d in encoder_depths)
        self.decoder_dims = tuple(tuple(int(v) for v in d) for d in decoder_dims)
        self.head_hidden_dim = int(head_hidden_dim)
        self.zero_init_output = bool(zero_init_output)

        # Pillar indices and offsets always in float32 (a bfloat16 x would move points across pillars).
        self.pillarize = L.Pillarize(num_pillars_x, num_pillars_y, x_range_m, y_range_m, z_range_m, name="pillarize",
                                     dtype="float32")
        self.point_encoder = L.PointEncoder(self.point_feature_dim, name="A")
        letters = iter(string.ascii_uppercase[2:] + "".join(f"E{i}" for i in range(100)))
        # Every layer is also a plain attribute (conv_C, ..., upsample_S, ...): TF checkpoints track attributes, not
        # the Keras-tracked lists below, so optimizer state and weights round-trip through tf.train.Checkpoint.
        self.encoder_stages = []
        for width, depth in zip(self.encoder_widths, self.encoder_depths):
            stage = []
            for i in range(depth):
                block = L.ConvBlock(width, strides=2 if i == 0 else 1, name=next(letters))
                setattr(self, f"conv_{block.name}", block)
                stage.append(block)
            self.encoder_stages.append(stage)
        self.upsample_skips = []
        for (d, db), n in zip(self.decoder_dims, "STU"):
            setattr(self, f"upsample_{n}", L.UpsampleSkip(d, db, name=n))
            self.upsample_skips.append(getattr(self, f"upsample_{n}"))
        self.conv_v = keras.layers.Conv2D(self.decoder_dims[-1][0], 3, padding="same", use_bias=False,
                                          kernel_initializer="glorot_uniform", name="V")
        self.head_y = L.UngridHead(self.head_hidden_dim, name="Y")
        self.head_z = keras.layers.Dense(3, kernel_initializer="zeros" if self.zero_init_output else "glorot_uniform",
                                         name="Z")

    def build(self, input_shape=None):
        """Creates every variable from the configuration alone (the shapes depend on the grid, not on the inputs)."""
        del input_shape
        h, w, c = self.num_pillars_y, self.num_pillars_x, self.point_feature_dim
        self.point_encoder.build((None, None, 8))
        shape = (None, h, w, c)
        skip_shapes = [shape]
        for stage in self.encoder_stages:
            for block in stage:
                block.build(shape)
                shape = tuple(block.conv.compute_output_shape(shape))
            skip_shapes.append(shape)

        def both(sh):
            return sh[:-1] + (2 * sh[-1],)
        x_shape = both(skip_shapes[3])
        for block, skip in zip(self.upsample_skips, (skip_shapes[2], skip_shapes[1], skip_shapes[0])):
            block.build((x_shape, both(skip)))
            x_shape = both(skip)[:-1] + (block.depth,)
        self.conv_v.build(x_shape)
        self.head_y.build(((None, h, w, self.conv_v.filters), (None, None, c), (None, None, 8)))
        self.head_z.build((None, None, self.head_hidden_dim))
        self.built = True

    def call(self, inputs, training=False):
        batch = tf.shape(inputs["points_xyz_t0"])[0]
        enc_t0, ids_t0, valid_t0 = self.pillarize(inputs["points_xyz_t0"], inputs["point_features_t0"],
                                                  tf.cast(inputs["point_mask_t0"], tf.bool))
        enc_tm1, ids_tm1, valid_tm1 = self.pillarize(inputs["points_xyz_tm1_in_t0"], inputs["point_features_tm1"],
                                                     tf.cast(inputs["point_mask_tm1"], tf.bool))
        # Row A on both clouds: shared weights and one set of BN statistics over both clouds (8-d, cheap), then
        # each cloud is encoded and scattered (row B) in chunks of points, so that memory does not grow with a full
        # [N, 64] feature array per cloud; the t0 chunks also yield the per-point part of row Y.
        normed_t0, normed_tm1 = self.point_encoder.norm([enc_t0, enc_tm1], [valid_t0, valid_tm1],
                                                        training=training)
        grid_t0, point_term_t0 = self._encode_cloud(normed_t0, valid_t0, ids_t0, batch, enc_t0)
        grid_tm1, _ = self._encode_cloud(normed_tm1, valid_tm1, ids_tm1, batch, None)
        bev = tf.cast(tf.concat([grid_t0, grid_tm1], 0), self.conv_v.compute_dtype)  # [2B,H,W,C], t0 samples first

        skips = [bev]
        x = bev
        for stage in self.encoder_stages:
            for block in stage:
                x = block(x, training=training)
            skips.append(x)

        def both(t):  # [2B,h,w,c] -> [B,h,w,2c], t0 first
            return tf.concat([t[:batch], t[batch:]], -1)

        # skips: B, F, L, R (paper rows); decoder S(R*, L*), T(S, F*), U(T, B*), V(U).
        x = self.upsample_skips[0]([both(skips[3]), both(skips[2])])
        x = self.upsample_skips[1]([x, both(skips[1])])
        x = self.upsample_skips[2]([x, both(skips[0])])
        grid_flow_embedding = self.conv_v(x)  # [B,H,W,64]
        y = self.head_y([grid_flow_embedding, point_term_t0, ids_t0])
        flow = tf.cast(self.head_z(y), tf.float32)
        flow = tf.where(valid_t0[..., None], flow, tf.zeros_like(flow))
        return {"flow_mps": flow, "point_valid": valid_t0}

    def _encode_cloud(self, normed, valid, pillar_ids, batch, encoding_for_head):
        """Rows A (after its BN) and B for one cloud, POINT_CHUNK points at a time.

        normed [B,N,8] (BN applied), valid [B,N], pillar_ids [B,N] (dummy B*H*W) -> grid [B,H,W,C] and, when
        `encoding_for_head` [B,N,8] is given, the head's per-point term [B,N,U]. The B*N points are flattened (ids
        are global over the batch), padded to whole chunks and taken chunk by chunk: no transposes, and memory for
        only one chunk's [chunk, C] features.
        """
        n = tf.shape(normed)[1]
        total_static = normed.shape[0] * normed.shape[1] if None not in normed.shape[:2] else None
        total = batch * n
        if total_static is not None:
            chunk = max(min(POINT_CHUNK, total_static), 1)
            num_chunks = max(-(-total_static // chunk), 1)
        else:
            chunk = tf.maximum(tf.minimum(POINT_CHUNK, total), 1)
            num_chunks = tf.maximum((total + chunk - 1) // chunk, 1)
        pad = num_chunks * chunk - total
        cells = self.num_pillars_x * self.num_pillars_y

        def chunks(t, fill):  # [B,N,...] -> [K,chunk,...]
            flat = tf.reshape(t, tf.concat([[total], tf.shape(t)[2:]], 0))
            flat = tf.pad(flat, [[0, pad]] + [[0, 0]] * (len(t.shape) - 2), constant_values=fill)
            return tf.reshape(flat, tf.concat([[num_chunks, chunk], tf.shape(t)[2:]], 0))

        normed_c = chunks(normed, 0.0)
        valid_c = chunks(valid, False)
        ids_c = chunks(pillar_ids, batch * cells)
        enc_c = chunks(encoding_for_head, 0.0) if encoding_for_head is not None else None
        c, u = self.point_feature_dim, self.head_hidden_dim
        dtype = self.point_encoder.dense.compute_dtype
        grid = tf.zeros([batch * cells + 1, c], dtype)
        # Plain tensor loop state (no TensorArray: its lists do not differentiate under XLA).
        terms = tf.zeros([num_chunks if enc_c is not None else 1, chunk, u], dtype)

        def body(i, grid, terms):
            feat = self.point_encoder.features(normed_c[i], valid_c[i])  # [chunk,C]
            # Row B, Snap-To-Grid: segment sum over flat pillar ids (dummy segment last for invalid points).
            grid = grid + tf.math.unsorted_segment_sum(feat, ids_c[i], batch * cells + 1)
            if enc_c is not None:
                terms = tf.tensor_scatter_nd_update(terms, [[i]], self.head_y.point_term(feat, enc_c[i])[None])
            return [i + 1, grid, terms]

        def cond(i, grid, terms):
            del grid, terms
            return i < num_chunks

        _, grid, terms = tf.while_loop(cond, body, [tf.constant(0), grid, terms], maximum_iterations=num_chunks)
        grid = tf.reshape(grid[:-1], [batch, self.num_pillars_y, self.num_pillars_x, c])
        if enc_c is None:
            return grid, None
        return grid, tf.reshape(tf.reshape(terms, [-1, u])[:total], [batch, n, u])

    def table_rows(self) -> list[tuple[str, int]]:
        """(row, parameter count) in the order of the paper's table."""
        rows = [("A", self.point_encoder.count_params()), ("B", 0)]
        rows += [(b.name, b.count_params()) for stage in self.encoder_stages for b in stage]
        rows += [(u.name, u.count_params()) for u in self.upsample_skips]
        rows += [("V", self.conv_v.count_params()), ("W", 0), ("X", 0), ("Y", self.head_y.count_params()),
                 ("Z", self.head_z.count_params())]
        return rows

    def get_config(self):
        return {**super().get_config(), "num_pillars_x": self.num_pillars_x, "num_pillars_y": self.num_pillars_y,
                "x_range_m": self.x_range_m, "y_range_m": self.y_range_m, "z_range_m": self.z_range_m,
                "point_feature_dim": self.point_feature_dim, "encoder_widths": self.encoder_widths,
                "encoder_depths": self.encoder_depths, "decoder_dims": self.decoder_dims,
                "head_hidden_dim": self.head_hidden_dim, "zero_init_output": self.zero_init_output}


def build_model(cfg: ExperimentConfig) -> FastFlow3D:
    """The model of a config, with its variables created (so count_params works before the first call)."""
    g, m = cfg.grid, cfg.model
    previous = keras.config.dtype_policy()
    # Mixed precision: bfloat16 compute, float32 variables (no loss scaling needed); the layers take the policy that
    # is global while they are constructed.
    keras.config.set_dtype_policy("mixed_bfloat16" if m.mixed_precision else "float32")
    try:
        # The model itself stays float32 so that it does not cast the input points (only its layers compute in
        # the mixed policy).
        model = FastFlow3D(g.num_pillars_x, g.num_pillars_y, g.x_range_m, g.y_range_m, g.z_range_m,
                           m.point_feature_dim, m.encoder_widths, m.encoder_depths, m.decoder_dims,
                           m.head_hidden_dim, m.zero_init_output, dtype="float32")
    finally:
        keras.config.set_dtype_policy(previous)
    # Variables from the configuration, without a forward pass: an eager dummy forward would allocate full-size
    # grids (~0.75 GB at 512 x 512) that the allocator then keeps for the life of the process.
    model.build()
    return model

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
        self.scatter = L.ScatterToGrid(num_pillars_x, num_pillars_y, name="B")
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

    def call(self, inputs, training=False):
        batch = tf.shape(inputs["points_xyz_t0"])[0]
        enc_t0, ids_t0, valid_t0 = self.pillarize(inputs["points_xyz_t0"], inputs["point_features_t0"],
                                                  tf.cast(inputs["point_mask_t0"], tf.bool))
        enc_tm1, ids_tm1, valid_tm1 = self.pillarize(inputs["points_xyz_tm1_in_t0"], inputs["point_features_tm1"],
                                                     tf.cast(inputs["point_mask_tm1"], tf.bool))
        # Row A on both clouds (shared weights, one set of BN statistics over both), one cloud at a time so that
        # only one cloud's 64-d point features are alive at once; each is scattered (row B) right away and the t0
        # cloud's per-point part of row Y is taken before its features are dropped.
        feat_t0, feat_tm1 = self.point_encoder([enc_t0, enc_tm1], [valid_t0, valid_tm1], training=training)
        if not self.head_y.built:
            self.head_y.build((tuple(feat_t0.shape[:-1]) + (self.decoder_dims[-1][0],), feat_t0.shape,
                               enc_t0.shape))
        point_term_t0 = self.head_y.point_term(feat_t0, enc_t0)  # [B,N0,32]
        grid_t0 = self.scatter(feat_t0, ids_t0, batch)
        grid_tm1 = self.scatter(feat_tm1, ids_tm1, batch)
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
    # Create the variables by tracing a call (nothing runs): an eager dummy forward would allocate full-size grids
    # (~0.75 GB at 512 x 512) that the allocator then keeps for the process' life.
    tf.function(lambda inputs: model(inputs)).get_concrete_function(input_specs())
    return model


def input_specs() -> dict[str, tf.TensorSpec]:
    """TensorSpecs of the batched model input (any batch size and point counts)."""
    return {"points_xyz_t0": tf.TensorSpec([None, None, 3], tf.float32),
            "point_features_t0": tf.TensorSpec([None, None, 2], tf.float32),
            "point_mask_t0": tf.TensorSpec([None, None], tf.bool),
            "points_xyz_tm1_in_t0": tf.TensorSpec([None, None, 3], tf.float32),
            "point_features_tm1": tf.TensorSpec([None, None, 2], tf.float32),
            "point_mask_tm1": tf.TensorSpec([None, None], tf.bool)}


def dummy_inputs(batch: int, num_points: int) -> dict[str, tf.Tensor]:
    pts = tf.zeros([batch, num_points, 3])
    feats = tf.zeros([batch, num_points, 2])
    mask = tf.ones([batch, num_points], tf.bool)
    return {"points_xyz_t0": pts, "point_features_t0": feats, "point_mask_t0": mask,
            "points_xyz_tm1_in_t0": pts, "point_features_tm1": feats, "point_mask_tm1": mask}

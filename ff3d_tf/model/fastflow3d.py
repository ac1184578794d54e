"""FastFlow3D (Jund et al., Sec. 4 and the appendix architecture table) as a Keras 3 model.

Inputs (dict, batched and padded; see `ff3d_tf.schema`):
  points_xyz_t0 [B,N0,3], point_features_t0 [B,N0,2], point_mask_t0 [B,N0] bool,
  points_xyz_tm1_in_t0 [B,N1,3], point_features_tm1 [B,N1,2], point_mask_tm1 [B,N1] bool;
  with `num_frames` > 2 also the older sweeps' points_xyz_tm{k}_in_t0, point_features_tm{k}, point_mask_tm{k}
  (`schema.model_input_keys`).
Outputs (dict): flow_mps [B,N0,3] (m/s, vehicle frame at t0; 0 where invalid), point_valid [B,N0] bool.

Both clouds share the point encoder (A) and the convolutional encoder (C-R): the two frames are stacked along the
batch axis and pass through the same layers once. The decoder (S, T, U, V) takes the depth-wise concatenation of the
two encoders' layers (t0 first), and the head (W-Z) regresses flow for the t0 points. Other heads replace rows W-Z
(`head`, `ff3d_tf.model.heads`: DeFlow's GRU point decoder, DeltaFlow's point MLP).

More sweeps (`temporal`, `model.temporal` in `ff3d_tf.config`; `ff3d_tf.model.fusions`): every sweep shares rows A
and B; `stack` passes every sweep through the encoder and the decoder concatenates all of them (the pair's
concatenation extended; the pair is `stack` with 2 sweeps); `delta` feeds the U-Net DeltaFlow's decayed difference of
the pillar grids alone, so its width stays C whatever the number of sweeps.

Precision: the dense stages (rows C-V) compute in the execution plan's precision (`ff3d_tf.model.plan`: bfloat16 for
`model.mixed_precision` resolved to it, see `ff3d_tf.model.compile`); the point stages (rows A, B, W-Z: coordinates,
pillar indices, point encoder, pillar sums, head) are float32 layers in every precision, and so are all variables.
"""
from __future__ import annotations

import logging
import string

import keras
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.config import ExperimentConfig, partner_matters
from ff3d_tf.model import compile as compile_lib
from ff3d_tf.model import fusions, heads
from ff3d_tf.model import layers as L
from ff3d_tf.model import ops
from ff3d_tf.model import plan as plan_lib

_LOG = logging.getLogger(__name__)


@keras.saving.register_keras_serializable(package="ff3d_tf")
class FastFlow3D(keras.Model):
    """The network of the paper's table, with two forwards that compute the same values up to float rounding:

    `table_forward`: rows A to Z in the table's order, one call per row, as a reader holds it beside the paper;
    the fused forward (`fused_forward`): the same arithmetic in the cheaper forms of the execution plan, in three
    stages with their own entry points, `encode_points` (rows A, B, and the points' own share of rows Y-Z),
    `grid_stages` (rows C-V, and the head's share of each cell) and `decode_points` (rows W-Z).

    `plan` (`ff3d_tf.model.plan.ExecutionPlan`, or its dict) says which forward `call` runs, in which forms, in which
    precision, and how a traced call (inside any `tf.function`) compiles it (`compile_mode`):
      "xla"    the whole forward as one XLA program;
      "hybrid" the fused forward's two point stages as their own XLA programs, the dense stages as TensorFlow graph
               kernels (oneDNN on CPU, faster there than XLA's); the table forward runs as "none";
      "none"   no XLA.
    Eager calls run op by op in every mode, and a caller that compiles the whole call with XLA passes
    `inline_stages=True` (one program, whatever the mode). `ff3d_tf.model.plan.resolve` makes the plan of a config.
    `plan.precision` (float32 or bfloat16) is the compute dtype of the dense stages (rows C-V, `conv_dtype`); the point
    stages are float32 layers in every precision.
    `point_chunk_size`: points (over the flattened batch) that the point encoder encodes and scatters at a time, and
    that the GRU head decodes at a time.
    `head`: the per-point head's unit (`ff3d_tf.model.heads.HEADS`): "paper" (rows W-Z: `head_y`, `head_z`), "gru"
    (`head_gru`: DeFlow's GRU point decoder, `gru_iterations` steps, an MLP of `head_hidden_dim` hidden units to the
    flow) or "mlp" (`head_mlp`: DeltaFlow's point head, `head_hidden_dim` wide).
    `num_frames`, `temporal`, `temporal_decay`, `partner`: the sweeps read, how they meet in the U-Net
    (`ff3d_tf.model.fusions.FUSIONS`) and which side of t0 the partner sweep lies on (`schema.PARTNERS`).
    """

    # Keyword-only, the paper's values without defaults: they live in `ff3d_tf.config` alone (`model_kwargs`).
    def __init__(self, *, num_pillars_x, num_pillars_y, x_range_m, y_range_m, z_range_m, point_feature_dim,
                 encoder_widths, encoder_depths, decoder_dims, head_hidden_dim, zero_init_output=False,
                 plan=None, point_chunk_size=ops.POINT_CHUNK, head="paper", gru_iterations=4, num_frames=2,
                 temporal="pair", temporal_decay=0.4, partner="previous", **kwargs):
        super().__init__(**kwargs)
        self.num_pillars_x, self.num_pillars_y = int(num_pillars_x), int(num_pillars_y)
        self.x_range_m, self.y_range_m, self.z_range_m = tuple(x_range_m), tuple(y_range_m), tuple(z_range_m)
        self.point_feature_dim = int(point_feature_dim)
        self.encoder_widths = tuple(int(w) for w in encoder_widths)
        self.encoder_depths = tuple(int(d) for d in encoder_depths)
        self.decoder_dims = tuple(tuple(int(v) for v in d) for d in decoder_dims)
        self.head_hidden_dim = int(head_hidden_dim)
        self.zero_init_output = bool(zero_init_output)
        self.plan = plan_lib.ExecutionPlan.from_dict(plan) if isinstance(plan, dict) else (
            plan or plan_lib.ExecutionPlan())
        self.point_chunk_size = int(point_chunk_size)
        if head not in heads.HEADS:
            raise ValueError(f"head={head!r}: one of {', '.join(heads.HEADS)}")
        self.head, self.gru_iterations = head, int(gru_iterations)
        self.head_unit = heads.HEADS[head]
        self.num_frames, self.temporal, self.temporal_decay = int(num_frames), temporal, float(temporal_decay)
        if temporal not in fusions.FUSIONS or not (fusions.FUSIONS[temporal].frames[0] <= self.num_frames <=
                                                   fusions.FUSIONS[temporal].frames[1]):
            raise ValueError(f"temporal={temporal!r} with num_frames={num_frames}: "
                             + ", ".join(f"{f.name} reads {f.frames[0]} to {f.frames[1]} sweeps"
                                         for f in fusions.FUSIONS.values()))
        self.fusion = fusions.FUSIONS[temporal]
        self.partner = partner
        self.slots_newest_first = schema.slots_newest_first(self.num_frames, partner)
        self.clouds = schema.sweep_clouds(self.num_frames)
        # The U-Net's branches: the sweeps it encodes with shared weights, stacked on the batch axis, whose layers
        # the decoder concatenates depth-wise (pair: the two clouds; stack: every sweep; delta: the one delta grid).
        self.branches = self.fusion.branches(self.num_frames)

        # The point stages in float32 under any global policy: pillar indices and offsets (a bfloat16 x would move
        # points across pillars), the point encoder and its pillar sums, and the head. XLA's CPU backend has no
        # bfloat16 arithmetic of its own (it converts to float32 and back), so bfloat16 would not make them faster.
        self.pillarize = L.Pillarize(num_pillars_x, num_pillars_y, x_range_m, y_range_m, z_range_m, name="pillarize",
                                     dtype="float32")
        self.point_encoder = L.PointEncoder(self.point_feature_dim, self.num_pillars_x, self.num_pillars_y,
                                            chunk_size=self.point_chunk_size, name="A", dtype="float32")
        # The dense stages compute in the plan's precision (bfloat16: float32 variables, no loss scaling needed, as
        # bfloat16 has float32's exponent range); Keras layers take the policy that is global while they are made.
        previous = keras.config.dtype_policy()
        keras.config.set_dtype_policy("mixed_bfloat16" if self.plan.precision == "bfloat16" else "float32")
        try:
            self._make_dense_stages()
        finally:
            keras.config.set_dtype_policy(previous)
        self.head_unit.make_layers(self)  # rows W-Z, or another head's layers (`ff3d_tf.model.heads`)

    def _make_dense_stages(self):
        """Rows C-V, each convolution told the plan's forms (`layers.Conv2D`, `layers.ConvBlock`)."""
        plan = self.plan
        letters = iter(string.ascii_uppercase[2:] + "".join(f"E{i}" for i in range(100)))
        # Every layer is also a plain attribute (conv_C, ..., upsample_S, ...): TF checkpoints track attributes, not
        # the Keras-tracked lists below, so optimizer state and weights round-trip through tf.train.Checkpoint.
        self.encoder_stages = []
        for width, depth in zip(self.encoder_widths, self.encoder_depths):
            stage = []
            for i in range(depth):
                block = L.ConvBlock(width, strides=2 if i == 0 else 1, name=next(letters))
                block.fold_batch_norm = plan.fold_batch_norm
                setattr(self, f"conv_{block.name}", block)
                stage.append(block)
            self.encoder_stages.append(stage)
        self.upsample_skips = []
        for (d, db), n in zip(self.decoder_dims, "STU"):
            setattr(self, f"upsample_{n}", L.UpsampleSkip(d, db, name=n))
            self.upsample_skips.append(getattr(self, f"upsample_{n}"))
        self.conv_v = L.Conv2D(self.decoder_dims[-1][0], 3, padding="same", use_bias=False,
                               kernel_initializer="glorot_uniform", name="V")
        convolutions = ([b.conv for s in self.encoder_stages for b in s] + [self.conv_v] +
                        [c for u in self.upsample_skips for c in (u.u1, u.u3, u.u5, u.u6)])
        for conv in convolutions:
            conv.matmul_1x1, conv.stride2_phase_gradients = plan.matmul_1x1, plan.stride2_phase_gradients

    @property
    def compile_mode(self) -> str:
        """The plan's compile mode: "xla", "hybrid" or "none"."""
        return self.plan.compile_mode

    @property
    def conv_dtype(self) -> str:
        """"float32" or "bfloat16": the compute dtype of the dense stages (rows C-V)."""
        return self.conv_v.compute_dtype

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
                shape = tuple(block.compute_output_shape(shape))
            skip_shapes.append(shape)

        def both(sh):
            return sh[:-1] + (self.branches * sh[-1],)
        x_shape = both(skip_shapes[3])
        for block, skip in zip(self.upsample_skips, (skip_shapes[2], skip_shapes[1], skip_shapes[0])):
            block.build((x_shape, both(skip)))
            x_shape = both(skip)[:-1] + (block.depth,)
        self.conv_v.build(x_shape)
        self.head_unit.build(self, [(None, h, w, c)] * self.fusion.head_grid_count(self.num_frames))
        self.built = True

    def call(self, inputs, training=False, inline_stages=False):
        """`inline_stages=True`: the caller compiles this whole call with XLA (`tf.function(jit_compile=True)`, at any
        depth), so the stages are traced inline as plain ops, whatever `compile_mode`. Every such caller must pass it
        (see `ff3d_tf.model.compile`)."""
        inputs = {k: inputs[k] for k in schema.model_input_keys(self.num_frames)}
        forward = self.table_forward if self.plan.forward == "table" else self.fused_forward
        if self.compile_mode == "none" or tf.executing_eagerly() or inline_stages:
            return forward(inputs, training)
        # A fresh function per trace of the caller: the stage reads the variables (or, under `stateless_call`, the
        # values that stand in for them) of the graph being traced.
        if self.compile_mode == "xla":
            return compile_lib.xla_function(lambda x: forward(x, training))(inputs)
        if self.plan.forward == "table":
            return forward(inputs, training)
        encoded = compile_lib.hybrid_encode(self.encode_points, inputs, training, self.plan.point_programs)
        grid = self.grid_stages(encoded["bev_features"], training)
        return compile_lib.xla_function(lambda g, e: self.decode_points(g, e, training))(grid, encoded)

    # -- the table forward -------------------------------------------------------------------------------------------

    def table_forward(self, inputs, training=False):
        """The paper's table, row by row: the model inputs (module docstring) -> flow_mps [B,N0,3] (0 where invalid),
        point_valid [B,N0]. Every convolution as the table lists it, whatever the plan's forms."""
        keys = [schema.cloud_keys(cloud) for cloud in self.clouds]  # t0, tm1 (and older sweeps), in slot order
        # Pillarize (the input of rows A and B): the 8-D encoding, the flat pillar id and validity of every point.
        encodings, ids, valid = zip(*[self.pillarize(inputs[k["xyz"]], inputs[k["features"]],
                                                     tf.cast(inputs[k["mask"]], tf.bool)) for k in keys])
        encoding_t0, ids_t0, valid_t0 = encodings[0], ids[0], valid[0]
        # A: per-point features [B,N,C] of every cloud (shared weights, one set of BN statistics).
        features = self.point_encoder.point_features(list(encodings), list(valid), training=training)
        # B: Snap-To-Grid, the pillar sums [B,H,W,C] of each cloud; the U-Net's input of them (the fusion's,
        # `ff3d_tf.model.fusions`): with the pair, both clouds stacked on the batch axis, t0 first [2B,H,W,C].
        grids = [ops.pillar_sums(f, i, self.num_pillars_y, self.num_pillars_x) for f, i in zip(features, ids)]
        bev, extra = self.fusion.encode(self, grids, ids, valid, for_head=self.head_unit.reads_pillar_grids)
        # C-R: three encoder stages of ConvBlocks (3x3 convolution, BatchNorm, ReLU); the first of each has stride 2.
        x, skips = bev, [bev]
        for stage in self.encoder_stages:
            for block in stage:
                x = block(x, training=training)
            skips.append(x)
        # S, T, U: Upsample-Skip blocks on the depth-wise concatenation of the branches' encoder outputs (the pair:
        # the two clouds').
        upsample_s, upsample_t, upsample_u = self.upsample_skips
        both = self._branches_concat
        x = upsample_s([both(skips[3]), both(skips[2])])
        x = upsample_t([x, both(skips[1])])
        x = upsample_u([x, both(skips[0])])
        # V: 3x3 convolution, the flow embedding of every cell [B,H,W,C_V].
        v = self.conv_v(x)
        # W-Z: the head (the paper's rows, or another head's layers: `ff3d_tf.model.heads`).
        t0 = {"features": features[0], "encoding": encoding_t0, "pillar_ids": ids_t0, "point_valid": valid_t0,
              "point_rows": self.pillarize.point_rows(inputs["points_xyz_t0"], inputs["point_features_t0"])}
        head_grids = self.fusion.head_grids(self, bev, extra) if self.head_unit.reads_pillar_grids else []
        flow = self.head_unit.table(self, v, t0, head_grids, training)
        return {"flow_mps": tf.where(valid_t0[..., None], flow, tf.zeros_like(flow)), "point_valid": valid_t0}

    def _branches_concat(self, t):
        """[S B,h,w,c] (the U-Net's S branches on the batch axis, t0 first) -> [B,h,w,S c], the branches' layers
        concatenated depth-wise, t0 first (split: its gradient is a concat, no zero-filled grids)."""
        return t if self.branches == 1 else tf.concat(tf.split(t, self.branches, axis=0), -1)

    # -- the fused forward -------------------------------------------------------------------------------------------

    def fused_forward(self, inputs, training=False):
        """The table's values in the plan's forms: `encode_points`, `grid_stages`, `decode_points`."""
        encoded = self.encode_points(inputs, training)
        return self.decode_points(self.grid_stages(encoded["bev_features"], training), encoded, training)

    def encode_points(self, inputs, training=False, stage=None):
        """Rows A and B on both clouds (shared weights, one set of BN statistics over both), and the part of the head
        that needs no grid.

        Rows Y and Z are linear with nothing between them, so the head is one linear map of (cell embedding, point
        feature, encoding) (`UngridHead.composed_with`); each t0 point's own share of the flow is taken while its
        features are computed, chunk by chunk, so no [N0, C] feature array is kept for the head.

        Returns a dict: bev_features [2B,H,W,C] (t0 samples first, then t-1; the float32 pillar sums in
        `conv_dtype`, cast here so that XLA fuses the cast with the concatenation), and for the head: point_flow_t0
        [B,N0,3] (m/s, float32; the flow without the grid part and the bias; paper head) or point_rows_t0 [B,N0,5]
        (`Pillarize.point_rows`, from which the GRU head computes each chunk's offsets), pillar_ids_t0 [B,N0],
        point_valid_t0 [B,N0].
        `stage`: None (traced inline), or what makes each part its own program (`compile_lib.hybrid_encode`).
        """
        keys = [schema.cloud_keys(cloud) for cloud in self.clouds]
        clouds = [(inputs[k["xyz"]], inputs[k["features"]], tf.cast(inputs[k["mask"]], tf.bool)) for k in keys]
        ids, valid = zip(*[(stage or (lambda f: f))(self.pillarize.cells)(*cloud) for cloud in clouds])
        ids_t0, valid_t0 = ids[0], valid[0]
        point_rows = [self.pillarize.point_rows(xyz, features) for xyz, features, _ in clouds]
        # The point encoder encodes each chunk of points itself (`Pillarize.encode`): no [N, 8] encoding is stored.
        # The head's share of each t0 point's (feature, encoding), if it takes one, is computed there too.
        grids, (projected_t0, *_) = self.point_encoder(
            point_rows, list(valid), list(ids),
            point_projections=(self.head_unit.point_projection(self),) + (None,) * (len(ids) - 1),
            encode=self.pillarize.encode, training=training, stage=stage)
        bev, extra = self.fusion.encode(self, grids, ids, valid, for_head=self.head_unit.reads_pillar_grids)
        return {"bev_features": bev, **self.head_unit.encoded(self, projected_t0, point_rows[0]), **extra,
                "pillar_ids_t0": ids_t0, "point_valid_t0": valid_t0}

    def dense_stages(self, bev_features, training=False):
        """Rows C-V: bev_features [2B,H,W,C] (t0 samples first; any float dtype, cast to `conv_dtype`) -> grid flow
        embedding [B,H,W,C_V] in `conv_dtype`. (The fused forward runs `grid_stages`.)"""
        return self.conv_v(self.unet(bev_features, training))

    def grid_stages(self, bev_features, training=False):
        """What the fused forward computes on the grid from bev_features [branches B,H,W,C]: the head's
        (`Head.grid_stages`): rows C-V (`dense_stages`), or with the paper head its grid part on each cell, cell_flow
        [B,H,W,3] float32 (m/s; without the points' own share and the bias), row V composed with it by the plan."""
        return self.head_unit.grid_stages(self, bev_features, training)

    def unet(self, bev_features, training=False, merged_last=False):
        """Rows C-U: bev_features [2B,H,W,C] (t0 samples first; any float dtype, cast to `conv_dtype`) -> row U's
        output [B,H,W,C_U] in `conv_dtype`; with `merged_last`, what row U's U5 convolves (`UpsampleSkip.merged`).
        `plan.remat_encoder`: training recomputes each encoder stage's activations in the backward pass;
        `plan.u6_into_next_u1`: rows S and T compute the next block's U1 with their U6 (`UpsampleSkip.into_next`)."""
        x = tf.cast(bev_features, self.conv_dtype)
        skips = [x]
        for stage in self.encoder_stages:
            if training and self.plan.remat_encoder:
                x = _rematerialized_stage(stage, x)
            else:
                for block in stage:
                    x = block(x, training=training)
            skips.append(x)
        # skips: B, F, L, R (paper rows); decoder S(R*, L*), T(S, F*), U(T, B*), V(U).
        s, t, u = self.upsample_skips
        both = self._branches_concat
        if not self.plan.u6_into_next_u1:
            x = t([s([both(skips[3]), both(skips[2])]), both(skips[1])])
            if merged_last:
                with tf.name_scope(u.name):
                    return u.merged([x, both(skips[0])])
            return u([x, both(skips[0])])
        # S's and T's outputs are read only by the next block's U1: each block computes that U1 itself.
        # (Methods called directly: each in its row's name scope, as a call would be.)
        with tf.name_scope(s.name):
            u1_of_t = s.into_next([both(skips[3]), both(skips[2])], t)
        with tf.name_scope(t.name):
            u1_of_u = t.into_next([None, both(skips[1])], u, u1=u1_of_t)
        with tf.name_scope(u.name):
            u4 = u.merged([None, both(skips[0])], u1=u1_of_u)
            return u4 if merged_last else u.u6(u.u5(u4))

    def decode_points(self, grid, encoded, training=False):
        """Rows W-Z: flow of the t0 points. `grid` is `grid_stages`' output and `encoded` `encode_points`' dict;
        returns flow_mps [B,N0,3] (0 where invalid) and point_valid [B,N0] (`Head.decode`; the head's state reads
        the fusion's pillar grids where it reads any)."""
        valid = encoded["point_valid_t0"]
        head_grids = (self.fusion.head_grids(self, encoded["bev_features"], encoded)
                      if self.head_unit.reads_pillar_grids else [])
        flow = self.head_unit.decode(self, grid, encoded, head_grids, training)
        flow = tf.where(valid[..., None], flow, tf.zeros_like(flow))
        return {"flow_mps": flow, "point_valid": valid}

    def point_offsets(self, point_rows, point_valid):
        """[P,3]: (dx, dy, dz) in metres from the pillar centre, channels 3-5 of the encoding of `point_rows` [P,5]
        (`Pillarize.encode`), 0 where `point_valid` [P] is False."""
        return self.pillarize.encode(point_rows, point_valid)[:, 3:6]

    def table_rows(self) -> list[tuple[str, int]]:
        """(row, parameter count) in the order of the paper's table (another head: rows A-W, then the head's layers,
        `Head.table_rows`)."""
        rows = [("A", self.point_encoder.count_params()), ("B", 0)]
        rows += [(b.name, b.count_params()) for stage in self.encoder_stages for b in stage]
        rows += [(u.name, u.count_params()) for u in self.upsample_skips]
        return rows + [("V", self.conv_v.count_params()), ("W", 0)] + self.head_unit.table_rows(self)

    def get_config(self):
        return {**super().get_config(), "num_pillars_x": self.num_pillars_x, "num_pillars_y": self.num_pillars_y,
                "x_range_m": self.x_range_m, "y_range_m": self.y_range_m, "z_range_m": self.z_range_m,
                "point_feature_dim": self.point_feature_dim, "encoder_widths": self.encoder_widths,
                "encoder_depths": self.encoder_depths, "decoder_dims": self.decoder_dims,
                "head_hidden_dim": self.head_hidden_dim, "zero_init_output": self.zero_init_output,
                "plan": self.plan.to_dict(), "point_chunk_size": self.point_chunk_size, "head": self.head,
                "gru_iterations": self.gru_iterations, "num_frames": self.num_frames, "temporal": self.temporal,
                "temporal_decay": self.temporal_decay, "partner": self.partner}


def _rematerialized_stage(stage: list, x):
    """An encoder stage (ConvBlocks) in training whose activations the backward pass recomputes from the stage's input
    `x` instead of holding them (`tf.recompute_grad`: the recomputation waits on the stage's output gradient, so XLA
    neither merges it with the forward's run nor schedules it early). Only the forward's run assigns the moving
    statistics."""
    forward_run = [True]

    def run(x):
        batches = []
        for block in stage:
            with tf.name_scope(block.name):
                x, batch = block.forward(x, training=True)
            batches.append(batch)
        if forward_run[0]:
            forward_run[0] = False
            for block, batch in zip(stage, batches):
                if batch is not None:
                    block.update_moving_statistics(*batch)
        return x
    return tf.recompute_grad(run)(x)


def model_kwargs(cfg: ExperimentConfig) -> dict:
    """FastFlow3D's constructor keywords from the config's grid and model fields (by name, never by position)."""
    g, m = cfg.grid, cfg.model
    return dict(num_pillars_x=g.num_pillars_x, num_pillars_y=g.num_pillars_y, x_range_m=g.x_range_m,
                y_range_m=g.y_range_m, z_range_m=g.z_range_m, point_feature_dim=m.point_feature_dim,
                encoder_widths=m.encoder_widths, encoder_depths=m.encoder_depths, decoder_dims=m.decoder_dims,
                head_hidden_dim=m.head_hidden_dim, zero_init_output=m.zero_init_output, head=m.head,
                gru_iterations=m.gru_iterations, num_frames=cfg.data.num_frames, temporal=m.temporal,
                temporal_decay=m.temporal_decay, partner=cfg.data.partner or "previous")


def model_definition(cfg: ExperimentConfig) -> dict:
    """What a trained model computes beyond its variables' shapes, by config key: the keys whose change a checkpoint
    restores into silently (delta's grid is C wide at any number of sweeps) but whose model computes something else.
    The partner sweep's side only where it matters (`config.partner_matters`)."""
    definition = {"data.num_frames": cfg.data.num_frames, "model.temporal": cfg.model.temporal,
                  "model.head": cfg.model.head}
    if cfg.model.temporal == "delta":
        definition["model.temporal_decay"] = cfg.model.temporal_decay
    if cfg.model.head == "gru":
        definition["model.gru_iterations"] = cfg.model.gru_iterations
    if partner_matters(cfg):
        definition["data.partner"] = cfg.data.partner or "previous"
    return definition


def build_model(cfg: ExperimentConfig, compile_mode: str | None = None, point_chunk_size: int | None = None,
                job: str = "inference", plan: plan_lib.ExecutionPlan | None = None) -> FastFlow3D:
    """The model of a config, with its variables created (so count_params works before the first call).

    Its execution plan is `plan`, else the config's for `job` ("train" for the Trainer's model, "inference"
    otherwise) on the visible device (`plan_lib.resolve`; `compile_mode` overrides `cfg.model.compile`), logged:
    "model.compile=auto -> hybrid for inference", "model.mixed_precision=auto -> bfloat16 (...)", "execution plan:
    ...". `point_chunk_size` overrides the point encoder's chunk (default `ops.POINT_CHUNK`; tests take a small one).
    """
    if plan is None:
        plan, why = plan_lib.resolve(cfg.model, job=job, compile_mode=compile_mode)
        for line in ("compile", "precision", "hint"):
            if line in why:
                _LOG.info(why[line])
    _LOG.info("execution plan: %s", plan.describe())
    # The model itself stays float32 so that it does not cast the input points (its dense layers compute in the
    # plan's precision).
    model = FastFlow3D(**model_kwargs(cfg), plan=plan,
                       point_chunk_size=ops.POINT_CHUNK if point_chunk_size is None else point_chunk_size,
                       dtype="float32")
    # Variables from the configuration, without a forward pass: an eager dummy forward would allocate full-size
    # grids (~0.75 GB at 512 x 512) that the allocator then keeps for the life of the process.
    model.build()
    return model

"""FastFlow3D's per-point heads (`model.head`) as units: each says which layers it adds to the model, how the table
forward and the fused forward's three stages use them, which execution-plan forms it admits and its rows of the
table. A new head is one class here, its entry in `HEADS` and its name in `ff3d_tf.config.HEADS`
(`tests/model/test_units.py` ties the two).

What the model (`ff3d_tf.model.fastflow3d.FastFlow3D`, `m` below) asks of a head:
  table forward:  `table(m, v, t0, head_grids, training)`: flow of the t0 points from row V's output `v`, the t0
                  cloud's rows (`t0`: features [B,N0,C] of row A, encoding [B,N0,8], point_rows [B,N0,5],
                  pillar_ids, point_valid) and the fusion's pillar grids (`ff3d_tf.model.fusions`);
  fused forward:  `point_projection(m)`: a kernel [C + 8, U] that row A's chunk loop applies to each t0 point's
                  (feature, encoding) while it computes them (no [N0, C] array is kept), or None;
                  `encoded(m, projected_t0, point_rows_t0)`: what `decode` needs of the points;
                  `grid_stages(m, bev, training)`: what it needs of the grid (rows C-V, or fewer channels);
                  `decode(m, grid, encoded, head_grids, training)`: flow [B,N0,3] (m/s; the model zeroes invalid
                  points).
Layer names are the checkpoints' (`head_y`/`Y`, `head_z`/`Z`, `head_gru`/`gru`, `head_mlp`/`mlp`).
"""
from __future__ import annotations

import abc
import keras
import tensorflow as tf

from ff3d_tf.model import gru_head
from ff3d_tf.model import layers as L
from ff3d_tf.model import ops

_PKG = "ff3d_tf"
FLOW_WIDTH = 3  # flow (x, y, z) in m/s


class Head(abc.ABC):
    """The interface (module docstring). `composes_with_v`: the head's first layer is linear in row V's output with
    nothing between them, so the plan may compose them (`plan.v_with_head`, `plan.decoder_chain`).
    `reads_pillar_grids`: its state reads the fusion's pillar grids (`Fusion.head_grids`)."""

    name = ""
    composes_with_v = False
    reads_pillar_grids = False

    @abc.abstractmethod
    def make_layers(self, m) -> None:
        """Each unit's own (the module docstring)."""

    @abc.abstractmethod
    def build(self, m, head_grid_shapes: list) -> None:
        """Each unit's own (the module docstring)."""

    @abc.abstractmethod
    def table(self, m, v, t0: dict, head_grids: list, training: bool):
        """Each unit's own (the module docstring)."""

    def point_projection(self, m):
        return None

    @abc.abstractmethod
    def encoded(self, m, projected_t0, point_rows_t0) -> dict:
        """Each unit's own (the module docstring)."""

    def grid_stages(self, m, bev, training: bool):
        return m.dense_stages(bev, training)

    @abc.abstractmethod
    def decode(self, m, grid, encoded: dict, head_grids: list, training: bool):
        """Each unit's own (the module docstring)."""

    @abc.abstractmethod
    def table_rows(self, m) -> list[tuple[str, int]]:
        """Each unit's own (the module docstring)."""


class PaperHead(Head):
    """Rows W-Z of the paper's table: each t0 point takes its pillar's cell of row V (W), concatenated with its point
    feature and encoding (X), two linear layers (Y, Z). Rows Y and Z are one linear map (`UngridHead.composed_with`),
    so the fused forward takes the grid's share on the grid (3 values per cell) and each point's own share in row A's
    chunk loop."""

    name = "paper"
    composes_with_v = True

    def make_layers(self, m):
        m.head_y = L.UngridHead(m.head_hidden_dim, grid_channels=m.decoder_dims[-1][0],
                                point_channels=m.point_feature_dim, name="Y", dtype="float32")
        m.head_z = keras.layers.Dense(FLOW_WIDTH, kernel_initializer="zeros" if m.zero_init_output else
                                      "glorot_uniform", name="Z", dtype="float32")

    def build(self, m, head_grid_shapes):
        m.head_y.build((None, None, m.conv_v.filters + m.point_feature_dim + 8))
        m.head_z.build((None, None, m.head_hidden_dim))

    def table(self, m, v, t0, head_grids, training):
        # W: Ungrid, each t0 point takes its pillar's cell embedding [B,N0,C_V].
        cell_t0 = L.UngridHead.ungrid(tf.cast(v, tf.float32), t0["pillar_ids"])
        # X: concatenation with the point's feature (row A) and its 8-D encoding [B,N0,C_V + C + 8].
        x = tf.concat([cell_t0, t0["features"], t0["encoding"]], -1)
        # Y: linear to head_hidden_dim; Z: linear to the flow (m/s).
        return m.head_z(m.head_y(x))

    def point_projection(self, m):
        _, k_point, k_encoding, _ = m.head_y.composed_with(m.head_z)
        return tf.concat([k_point, k_encoding], 0)  # [C + 8, 3]: (point feature, encoding) -> flow

    def encoded(self, m, projected_t0, point_rows_t0):
        return {"point_flow_t0": tf.cast(projected_t0, tf.float32)}

    def grid_stages(self, m, bev, training):
        """The head's grid part on each cell, cell_flow [B,H,W,3] float32 (m/s; without the points' own share and
        the bias, `decode`).

        `plan.v_with_head`: row V (a 3x3 convolution) and the head's grid part (a linear map of V's channels to 3 for
        every cell) are both linear with nothing between them, so they are one 3x3 convolution to 3 channels whose
        kernel is V's composed with the head's: row V's arithmetic for 3 output channels instead of 64, forward and
        backward. It runs in float32 under every precision, as the head always has.

        `plan.decoder_chain`: row U's U5 and U6 (3x3 convolutions, linear with nothing between them and V either)
        join that convolution: row U's merged input to the 3 channels in one pass (`ops.conv_chain_same`: the three
        kernels composed into one 7x7 kernel, a matrix product to its 147 taps and shifted sums, the cells near the
        border by the chain itself), a fraction of the three convolutions' arithmetic."""
        k_grid = m.head_y.composed_with(m.head_z)[0]
        if not m.plan.v_with_head:
            return ops.dense_last_axis(tf.cast(m.dense_stages(bev, training), tf.float32), k_grid)
        with tf.name_scope(m.conv_v.name):
            kernel_v = tf.cast(m.conv_v.kernel, tf.float32)  # [3, 3, C_U, C_V]
            kernel = ops.dense_last_axis(kernel_v, tf.cast(k_grid, tf.float32))  # [3, 3, C_U, 3]
        if not m.plan.decoder_chain:
            return tf.nn.conv2d(tf.cast(m.unet(bev, training), tf.float32), kernel, 1, "SAME")
        last = m.upsample_skips[-1]
        u4 = m.unet(bev, training, merged_last=True)
        with tf.name_scope(m.conv_v.name):
            return ops.conv_chain_same(u4, [tf.cast(last.u5.kernel, tf.float32),
                                            tf.cast(last.u6.kernel, tf.float32), kernel])

    def decode(self, m, grid, encoded, head_grids, training):
        bias = m.head_y.composed_with(m.head_z)[3]
        return m.head_y.ungrid(grid, encoded["pillar_ids_t0"]) + encoded["point_flow_t0"] + bias

    def table_rows(self, m):
        return [("X", 0), ("Y", m.head_y.count_params()), ("Z", m.head_z.count_params())]


class GRUHead(Head):
    """DeFlow's GRU point decoder (`ff3d_tf.model.gru_head.GRUHead`, Zhang et al., ICRA 2024): each point's hidden
    state starts at its pillar's cells of the fusion's pillar grids and of row V's output, concatenated; its input is
    its offset from the pillar centre (channels 3-5 of `Pillarize.encode`, computed chunk by chunk from the point's
    5 input values). The grids enter in their own dtype (bfloat16 under mixed precision), one chunk of points at a
    time cast to the head's float32."""

    name = "gru"
    reads_pillar_grids = True

    def make_layers(self, m):
        m.head_gru = gru_head.GRUHead(input_units=m.point_feature_dim, mlp_units=m.head_hidden_dim,
                                      iterations=m.gru_iterations, chunk_size=m.point_chunk_size,
                                      zero_init_output=m.zero_init_output, name="gru", dtype="float32")

    def build(self, m, head_grid_shapes):
        h, w = m.num_pillars_y, m.num_pillars_x
        m.head_gru.build(list(head_grid_shapes) + [(None, h, w, m.conv_v.filters)])

    def _flow(self, m, grid, head_grids, point_rows_t0, pillar_ids_t0, point_valid_t0):
        return m.head_gru.decode([*head_grids, grid], point_rows_t0, pillar_ids_t0, point_valid_t0,
                                 encode=m.point_offsets)

    def table(self, m, v, t0, head_grids, training):
        return self._flow(m, v, head_grids, t0["point_rows"], t0["pillar_ids"], t0["point_valid"])

    def encoded(self, m, projected_t0, point_rows_t0):
        return {"point_rows_t0": point_rows_t0}

    def decode(self, m, grid, encoded, head_grids, training):
        return self._flow(m, grid, head_grids, encoded["point_rows_t0"], encoded["pillar_ids_t0"],
                          encoded["point_valid_t0"])

    def table_rows(self, m):
        return m.head_gru.table_rows()


@keras.saving.register_keras_serializable(package=_PKG)
class PointMLP(keras.layers.Layer):
    """DeltaFlow's point head (Zhang et al., NeurIPS 2025; KTH-RPL/OpenSceneFlow @848bf86
    `src/models/basic/flow4d_module.py` `Point_head`, lines 312-333): Linear(cell embedding + point feature -> U),
    BatchNorm, ReLU, Linear(U -> 3), on the concatenation of the point's cell of the backbone's output and the
    point's own feature. The normalisation's statistics are those of the valid points (`MaskedBatchNorm`).

    `hidden_kernel` [C_cell + C_point, U] splits into the cell's and the point's shares (`split_kernel`), so a caller
    can compute the point's share where the point feature is made and the cell's after the gather."""

    def __init__(self, units=32, cell_channels=64, point_channels=64, zero_init_output=False, **kwargs):
        super().__init__(**kwargs)
        self.units, self.cell_channels, self.point_channels = int(units), int(cell_channels), int(point_channels)
        self.zero_init_output = bool(zero_init_output)
        self.norm = L.MaskedBatchNorm(momentum=0.9, epsilon=1e-5, name="bn")  # torch BatchNorm1d's defaults
        self.output_layer = keras.layers.Dense(FLOW_WIDTH, kernel_initializer="zeros" if zero_init_output else
                                               "glorot_uniform", name="output")

    def build(self, input_shape=None):
        self.hidden_kernel = self.add_weight(name="hidden_kernel", shape=(self.cell_channels + self.point_channels,
                                                                          self.units), initializer="glorot_uniform")
        self.hidden_bias = self.add_weight(name="hidden_bias", shape=(self.units,), initializer="zeros")
        self.norm.build((None, self.units))
        self.output_layer.build((None, self.units))
        self.built = True

    def split_kernel(self):
        """(cell share [C_cell, U], point share [C_point, U]) of the hidden layer's kernel."""
        return self.hidden_kernel[:self.cell_channels], self.hidden_kernel[self.cell_channels:]

    def finish(self, hidden_without_bias, point_valid, training=False):
        """hidden [B,N,U] (the hidden layer's product, no bias) -> flow [B,N,3]: bias, BatchNorm over the valid points,
        ReLU, the output layer."""
        x = self.norm(hidden_without_bias + self.hidden_bias, point_valid, training=training)
        return self.output_layer(tf.nn.relu(x))

    def call(self, cell_and_point, point_valid, training=False):
        """[B,N,C_cell + C_point] -> flow [B,N,3]."""
        return self.finish(ops.dense_last_axis(cell_and_point, self.hidden_kernel), point_valid, training)

    def table_rows(self) -> list[tuple[str, int]]:
        return [("MLP-1", self.hidden_kernel.shape.num_elements() + self.units), ("MLP-BN", 4 * self.units),
                ("MLP-2", self.output_layer.count_params())]

    def get_config(self):
        return {**super().get_config(), "units": self.units, "cell_channels": self.cell_channels,
                "point_channels": self.point_channels, "zero_init_output": self.zero_init_output}


class MLPHead(Head):
    """DeltaFlow's default decoder (`PointMLP`): each t0 point's cell of row V and its point feature of row A, through
    Linear-BN-ReLU-Linear. The point feature's share of the first layer is taken in row A's chunk loop (the
    encoding's share is zero: the authors' head reads the point feature alone)."""

    name = "mlp"

    def make_layers(self, m):
        m.head_mlp = PointMLP(m.head_hidden_dim, cell_channels=m.decoder_dims[-1][0],
                              point_channels=m.point_feature_dim, zero_init_output=m.zero_init_output, name="mlp",
                              dtype="float32")

    def build(self, m, head_grid_shapes):
        m.head_mlp.build()

    def table(self, m, v, t0, head_grids, training):
        cell_t0 = L.UngridHead.ungrid(tf.cast(v, tf.float32), t0["pillar_ids"])
        return m.head_mlp(tf.concat([cell_t0, t0["features"]], -1), t0["point_valid"], training=training)

    def point_projection(self, m):
        k_point = m.head_mlp.split_kernel()[1]
        return tf.concat([k_point, tf.zeros([8, m.head_mlp.units], k_point.dtype)], 0)  # [C + 8, U]

    def encoded(self, m, projected_t0, point_rows_t0):
        return {"point_hidden_t0": tf.cast(projected_t0, tf.float32)}

    def decode(self, m, grid, encoded, head_grids, training):
        cell_t0 = L.UngridHead.ungrid(tf.cast(grid, tf.float32), encoded["pillar_ids_t0"])
        hidden = ops.dense_last_axis(cell_t0, m.head_mlp.split_kernel()[0]) + encoded["point_hidden_t0"]
        return m.head_mlp.finish(hidden, encoded["point_valid_t0"], training=training)

    def table_rows(self, m):
        return [("X", 0)] + m.head_mlp.table_rows()


HEADS = {head.name: head for head in (PaperHead(), GRUHead(), MLPHead())}  # model.head -> its unit

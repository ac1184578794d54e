"""DeFlow's GRU point decoder as FastFlow3D's per-point head (`model.head=gru`).

Zhang, Yang, Khoche, Jensfelt, "DeFlow: Decoder of Scene Flow Network in Autonomous Driving", ICRA 2024
(arXiv 2401.16122), Sec. III and Fig. 3: the paper head (rows W-Z) gives every point of a pillar the same grid
embedding and only a linear share of its own, which blurs the flow at object boundaries where one pillar holds points
of several objects. DeFlow refines each point with a gated recurrent unit (Cho et al., 2014) whose hidden state starts
at the point's pillar features and whose input is the point's own position in the pillar:

  h_0 = [pillar embedding at t0, pillar embedding at t-1, decoder output] of the point's pillar   [P, Hd]
  x   = linear(offset of the point from its pillar centre)                                         [P, I]
  z   = sigmoid([h, x] W_z + b_z)          update gate
  r   = sigmoid([h, x] W_r + b_r)          reset gate
  q   = tanh([r * h, x] W_q + b_q)         candidate
  h  <- (1 - z) * h + z * q                `iterations` times (the same weights each time)
  flow = W_2 GELU([h, x] W_1 + b_1) + b_2                                                          [P, 3]

With 0 iterations it is a plain MLP on [h_0, x]. Notation as in `ff3d_tf.model.layers`; P points flattened over the
batch, Hd the hidden width (the sum of the pillar grids' channels), I the input width, M the MLP's hidden width.

Each gate is a per-point dense layer on [h, x]; the code splits its kernel into the rows that multiply h and those
that multiply x, and computes the x part (which does not change between iterations) once per point.

Memory: the head runs `chunk_size` points at a time (`chunked_pillar_map`), forward and backward, like the point
encoder: no [N, Hd] array exists beyond one chunk at any cloud size, and the backward pass recomputes each chunk
under its own tape (the automatic gradient of a tf.while_loop would keep every chunk's iterations).
"""
from __future__ import annotations

import keras
import tensorflow as tf

from ff3d_tf.model import ops

_PKG = "ff3d_tf"
OUTPUT_WIDTH = 3  # flow (x, y, z) in m/s


def gelu(x):
    """GELU with the error function (Hendrycks and Gimpel, 2016; DeFlow's MLP), written with `erf` so that every
    export (ONNX: Erf) takes it as it is."""
    return 0.5 * x * (1.0 + tf.math.erf(x * tf.constant(0.7071067811865476, x.dtype)))


def chunked_pillar_map(fn, pillar_cells, pillar_ids, point_values, weights, chunk_size):
    """Per-point rows that `fn` computes `chunk_size` points at a time from each point's pillar features and its own
    values; with a gradient that recomputes each chunk.

    fn(pillar_features, point_values [P',D], in_pillar [P'] bool, weights) -> rows [P',U] for a chunk of P' points,
      where pillar_features is a list with one [P', C_i] per grid: the point's cell of each grid.
    pillar_cells: list of [cells, C_i] float tensors (the grids flattened over batch, rows and columns; any float
      dtype); pillar_ids: [P] int32 flat cell ids, -1 for points in no pillar (they read cell 0, `in_pillar` is
      False, their gradient is dropped); point_values: [P,D] float, not differentiated (a zero gradient); weights:
      tensors every chunk uses (their gradients are summed over the chunks).
    Returns rows [P,U].

    The grids' gradient is added into [cells, C_i] per chunk (a scatter-add into one array, in place in XLA), so
    backward, like forward, holds one chunk's features at a time. A static count of one chunk (`ops.ONE_CHUNK`, or a
    small static cloud) runs without a loop: the loop-free ONNX export.
    """
    num_grids = len(pillar_cells)
    total = tf.shape(pillar_ids)[0]
    chunk, num_chunks = ops._chunking(total, pillar_ids.shape[0], chunk_size)  # noqa: SLF001 (the model's helper)
    single = isinstance(num_chunks, int) and num_chunks == 1

    def to_chunks(t, fill):  # [P, ...] -> [K, chunk, ...]
        t = tf.pad(t, [[0, num_chunks * chunk - total]] + [[0, 0]] * (len(t.shape) - 1), constant_values=fill)
        return tf.reshape(t, tf.concat([[num_chunks, chunk], tf.shape(t)[1:]], 0))

    ids = to_chunks(pillar_ids, -1)

    def gather(cells, chunk_ids):  # the points' cells of every grid, [P', C_i] each
        return [tf.gather(c, tf.maximum(chunk_ids, 0)) for c in cells]

    @tf.custom_gradient
    def run(values, *tensors):  # values [K, chunk, D]
        cells, weights = list(tensors[:num_grids]), list(tensors[num_grids:])

        def chunk_rows(i):
            return fn(gather(cells, ids[i]), values[i], ids[i] >= 0, weights)

        if single:
            rows = chunk_rows(0)[None]
        else:  # an empty chunk gives the rows' width and dtype
            empty = fn(gather(cells, ids[0][:0]), values[0][:0], ids[0][:0] >= 0, weights)
            rows = ops._over_chunks(  # noqa: SLF001
                num_chunks, lambda i, r: tf.tensor_scatter_nd_update(r, [[i]], chunk_rows(i)[None]),
                tf.zeros([num_chunks, chunk, empty.shape[-1]], empty.dtype))

        def grad(d_rows):
            def backward(i, state):
                d_cells, d_weights = state
                chunk_ids = ids[i]
                features = gather(cells, chunk_ids)
                with tf.GradientTape() as tape:
                    tape.watch(features + weights)
                    rows = fn(features, values[i], chunk_ids >= 0, weights)
                d_features, d_chunk_weights = _split(tape.gradient(
                    rows, features + weights, output_gradients=d_rows[i],
                    unconnected_gradients=tf.UnconnectedGradients.ZERO), num_grids)
                # Added in float32 also for bfloat16 grids; points in no pillar add zero to cell 0.
                in_pillar = (chunk_ids >= 0)[:, None]
                index = tf.maximum(chunk_ids, 0)[:, None]
                d_cells = [tf.tensor_scatter_nd_add(d, index, tf.where(in_pillar, tf.cast(g, tf.float32), 0.0))
                           for d, g in zip(d_cells, d_features)]
                return d_cells, [d + tf.cast(g, tf.float32) for d, g in zip(d_weights, d_chunk_weights)]

            state = ([tf.zeros(tf.shape(c), tf.float32) for c in cells],
                     [tf.zeros(tf.shape(w), tf.float32) for w in weights])
            d_cells, d_weights = ops._over_chunks(num_chunks, backward, state)  # noqa: SLF001
            return ([tf.zeros_like(values)] + [tf.cast(d, c.dtype) for d, c in zip(d_cells, cells)] +
                    [tf.cast(d, w.dtype) for d, w in zip(d_weights, weights)])

        return rows, grad

    rows = run(to_chunks(point_values, tf.zeros([], point_values.dtype)), *pillar_cells, *weights)
    return tf.reshape(rows, [-1, rows.shape[-1]])[:total]


def _split(items, n):
    return list(items[:n]), list(items[n:])


@keras.saving.register_keras_serializable(package=_PKG)
class GRUHead(keras.layers.Layer):
    """DeFlow's GRU point decoder (module docstring): flow of each point from its pillar's features in several grids
    and its offset from the pillar centre.

    Args:
      input_units: I, the width of the learned linear encoding of the offset (the GRU's input).
      mlp_units: M, the hidden width of the output MLP.
      iterations: GRU steps (0: no gate weights, a plain MLP on [h_0, x]).
      chunk_size: points (over the flattened batch) decoded at a time.
      zero_init_output: zeros for the output layer's kernel (the head starts at the zero-flow prediction).
    The hidden width Hd is the sum of the grids' channels (known when built).
    Call:
      pillar_grids: list of [B,H,W,C_i] grids (any float dtype: cast to the compute dtype one chunk at a time);
      points [B,N,D]: the offsets from the pillar centres (x, y, z in metres, D = 3), or with `encode` the values it
      computes them from; pillar_ids [B,N] int32 (flat over the batch, as `Pillarize` gives them); point_valid [B,N]
      bool; encode: None, or a function (values [P,D], valid [P]) -> offsets [P,3] that each chunk applies to its
      points (the model passes the points' 5 input values and `Pillarize.encode`: no [N, 8] encoding is stored).
    Returns flow [B,N,3] in the compute dtype, 0 for invalid points.
    """

    def __init__(self, input_units=64, mlp_units=32, iterations=4, chunk_size=ops.POINT_CHUNK,
                 zero_init_output=False, **kwargs):
        super().__init__(**kwargs)
        self.input_units, self.mlp_units = int(input_units), int(mlp_units)
        self.iterations, self.chunk_size = int(iterations), int(chunk_size)
        self.zero_init_output = bool(zero_init_output)
        if self.iterations < 0:
            raise ValueError(f"iterations={iterations}: must be >= 0")

        # The layers are made in `build`, in the order they apply: the gates' width is Hd, the grids' channels.
        self.offset_encoder = self.update_gate = self.reset_gate = self.candidate = None
        self.mlp_hidden = self.mlp_output = None

    def build(self, pillar_grids_shape):
        """pillar_grids_shape: the grids' shapes [.., C_i]; Hd = sum of C_i."""
        self.grid_channels = tuple(int(s[-1]) for s in pillar_grids_shape)
        hidden = self.hidden_units

        def dense(units, name, input_width, kernel_initializer="glorot_uniform"):
            layer = keras.layers.Dense(units, kernel_initializer=kernel_initializer, name=name,
                                       dtype=self.dtype_policy)
            layer.build((None, input_width))
            return layer

        self.offset_encoder = dense(self.input_units, "offset_encoder", 3)
        if self.iterations:
            self.update_gate, self.reset_gate, self.candidate = [
                dense(hidden, name, hidden + self.input_units) for name in ("update_gate", "reset_gate", "candidate")]
        self.mlp_hidden = dense(self.mlp_units, "mlp_hidden", hidden + self.input_units)
        self.mlp_output = dense(OUTPUT_WIDTH, "mlp_output", self.mlp_units,
                                "zeros" if self.zero_init_output else "glorot_uniform")
        self.built = True

    @property
    def gates(self) -> list:
        """The update gate, reset gate and candidate layers (none with 0 iterations)."""
        return [self.update_gate, self.reset_gate, self.candidate] if self.iterations else []

    @property
    def hidden_units(self) -> int:
        """Hd: the width of the hidden state (the grids' channels together)."""
        return sum(self.grid_channels)

    def call(self, pillar_grids, points, pillar_ids, point_valid, encode=None):
        return self.decode(pillar_grids, points, pillar_ids, point_valid, encode)

    def decode(self, pillar_grids, points, pillar_ids, point_valid, encode=None):
        """`call` without Keras's input casting (the grids stay in their dtype: no cast copy of a whole grid)."""
        batch, n = tf.shape(points)[0], tf.shape(points)[1]
        cells = [tf.reshape(g, [-1, g.shape[-1]]) for g in pillar_grids]
        valid = tf.reshape(tf.cast(point_valid, tf.bool), [-1])
        ids = tf.where(valid, tf.reshape(pillar_ids, [-1]), -1)
        weights = self._chunk_weights(self.compute_dtype)

        def decode_chunk(pillar_features, values, in_pillar, weights):
            offsets = values if encode is None else encode(values, in_pillar)
            offsets = tf.where(in_pillar[:, None], tf.cast(offsets, self.compute_dtype), 0.0)
            return self._decode_chunk(pillar_features, offsets, weights)

        flow = chunked_pillar_map(decode_chunk, cells, ids, tf.reshape(points, [-1, points.shape[-1]]), weights,
                                  self.chunk_size)
        flow = tf.where(valid[:, None], flow, tf.zeros_like(flow))
        return tf.reshape(flow, [batch, n, OUTPUT_WIDTH])

    def _chunk_weights(self, dtype):
        """The variables as the chunk function takes them: the offset encoder; the input's share of the gates and of
        the MLP's hidden layer as one kernel [I, 3 Hd + M] with their biases (computed once per point); the hidden
        state's share of the update and reset gates [Hd, 2 Hd], of the candidate [Hd, Hd], of the MLP [Hd, M]; the
        output layer."""
        hd = self.hidden_units
        layers = self.gates + [self.mlp_hidden]
        input_kernel = tf.concat([layer.kernel[hd:] for layer in layers], 1)
        input_bias = tf.concat([layer.bias for layer in layers], 0)
        gate_kernels = ([tf.concat([self.update_gate.kernel[:hd], self.reset_gate.kernel[:hd]], 1),
                         self.candidate.kernel[:hd]] if self.iterations else [])
        weights = [self.offset_encoder.kernel, self.offset_encoder.bias, input_kernel, input_bias, *gate_kernels,
                   self.mlp_hidden.kernel[:hd], self.mlp_output.kernel, self.mlp_output.bias]
        return [tf.cast(w, dtype) for w in weights]

    def _decode_chunk(self, pillar_features, offsets, weights):
        """One chunk: pillar features [[P,C_i], ...] and offsets [P,3] -> flow [P,3] (module docstring)."""
        hd, dtype = self.hidden_units, offsets.dtype
        k_offset, b_offset, k_input, b_input = weights[:4]
        k_zr, k_q = weights[4:6] if self.iterations else (None, None)
        k_mlp, k_out, b_out = weights[-3:]
        hidden = tf.concat([tf.cast(f, dtype) for f in pillar_features], -1)  # h_0 [P,Hd]
        encoded_offset = ops.narrow_matmul(offsets, k_offset) + b_offset  # x [P,I]
        by_input = tf.matmul(encoded_offset, k_input) + b_input  # x's share with the biases [P, 3Hd + M]
        for _ in range(self.iterations):
            update_reset = tf.sigmoid(tf.matmul(hidden, k_zr) + by_input[:, :2 * hd])
            update, reset = update_reset[:, :hd], update_reset[:, hd:]
            candidate = tf.tanh(tf.matmul(reset * hidden, k_q) + by_input[:, 2 * hd:3 * hd])
            hidden = hidden + update * (candidate - hidden)  # (1 - z) h + z q
        mlp = gelu(tf.matmul(hidden, k_mlp) + by_input[:, -self.mlp_units:])
        return tf.matmul(mlp, k_out) + b_out

    def table_rows(self) -> list[tuple[str, int]]:
        """(row, parameter count) of the head's layers, in the order they apply."""
        rows = [("GRU-x", self.offset_encoder.count_params())]
        if self.iterations:
            rows += [("GRU-z", self.update_gate.count_params()), ("GRU-r", self.reset_gate.count_params()),
                     ("GRU-q", self.candidate.count_params())]
        return rows + [("MLP-1", self.mlp_hidden.count_params()), ("MLP-2", self.mlp_output.count_params())]

    def get_config(self):
        return {**super().get_config(), "input_units": self.input_units, "mlp_units": self.mlp_units,
                "iterations": self.iterations, "chunk_size": self.chunk_size,
                "zero_init_output": self.zero_init_output}

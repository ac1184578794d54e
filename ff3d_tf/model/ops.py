"""The model's operations that are not layers: the point encoder's chunk loop (`chunked_segment_sum`, `POINT_CHUNK`
points at a time by default, or the whole cloud at once with `ONE_CHUNK`), two matrix products shaped for XLA
(`dense_last_axis`, `narrow_matmul`), the grid's bilinear x2 upsampling (`bilinear_upsample_2x`) and a strided
convolution whose gradients XLA's CPU backend computes as stride-1 convolutions (`conv2d_stride2`).

Notation as in `ff3d_tf.model.layers`: P points (flattened over the batch), C channels.
"""
from __future__ import annotations

import tensorflow as tf

# Points per chunk of the point encoder's loop: bounds the [chunk, C] feature memory at any cloud size and keeps a
# chunk's traffic in cache.
POINT_CHUNK = 1 << 16
# A chunk size that no int32 point count exceeds: the whole cloud is one chunk, and the loop is left out of the graph
# also when the point count is known only at run time (a static count of one chunk always runs without a loop). The
# results are those of any chunk size; the graph has no while loop (the loop-free ONNX export for TensorRT).
ONE_CHUNK = (1 << 31) - 1


def pillar_sums(point_features, pillar_ids, num_pillars_y: int, num_pillars_x: int):
    """Row B, Snap-To-Grid: each pillar sums the features of its points. point_features [B,N,C], pillar_ids [B,N]
    flat over the batch (b*H*W + row*W + col), B*H*W for a point in no pillar: one extra segment takes those, and is
    dropped. Returns [B,H,W,C]."""
    batch, channels = tf.shape(point_features)[0], point_features.shape[-1]
    cells = batch * num_pillars_y * num_pillars_x
    sums = tf.math.unsorted_segment_sum(tf.reshape(point_features, [-1, channels]), tf.reshape(pillar_ids, [-1]),
                                        cells + 1)  # [B*H*W + 1, C]
    return tf.reshape(sums[:cells], [batch, num_pillars_y, num_pillars_x, channels])


def pillar_means(grid_sums, pillar_ids, point_valid):
    """Row B's pillar sums [B,H,W,C] of a cloud divided by each pillar's count of valid points (`point_valid` [B,N],
    `pillar_ids` [B,N] flat over the batch as `pillar_sums` takes them): the pillar means, 0 in an empty pillar."""
    batch, rows, columns = tf.shape(grid_sums)[0], grid_sums.shape[1], grid_sums.shape[2]
    ids = tf.where(point_valid, pillar_ids, batch * rows * columns)
    counts = pillar_sums(tf.cast(point_valid, grid_sums.dtype)[..., None], ids, rows, columns)
    return grid_sums / tf.maximum(counts, 1.0)


def dense_last_axis(x, kernel):
    """x [..., C] @ kernel [C, U] as one 2-D matmul (no tensordot transposes: inside the point-chunk loop those
    need compile-time shapes under XLA)."""
    kernel = tf.cast(kernel, x.dtype)
    out = tf.matmul(tf.reshape(x, [-1, tf.shape(x)[-1]]), kernel)
    return tf.reshape(out, tf.concat([tf.shape(x)[:-1], tf.shape(kernel)[-1:]], 0))


@tf.custom_gradient
def narrow_matmul(x, kernel):
    """x [P,K] @ kernel [K,C] for a small K (the 8-D encoding), as K products of a column and a row: XLA fuses them
    with the ops around them instead of writing the product out for a matrix multiply. The gradient is the usual
    pair of matrix products."""
    y = tf.add_n([x[:, j:j + 1] * kernel[j] for j in range(x.shape[-1])])

    def grad(dy):
        return tf.matmul(dy, kernel, transpose_b=True), tf.matmul(x, dy, transpose_a=True)

    return y, grad


def stride2_by_phases_applies(input_shape, kernel_shape, strides, padding) -> bool:
    """Whether `conv2d_stride2` computes this convolution: a 3x3 kernel, stride 2, SAME padding and an even static
    height and width of the input [B,H,W,C]."""
    h, w = input_shape[1], input_shape[2]
    return (tuple(kernel_shape[:2]) == (3, 3) and tuple(strides) == (2, 2) and str(padding).upper() == "SAME" and
            h is not None and w is not None and h % 2 == 0 and w % 2 == 0)


def conv2d_stride2(x, kernel):
    """`tf.nn.conv2d(x, kernel, 2, "SAME")` for x [B,H,W,Ci] with an even static H and W and a 3x3 kernel
    [3,3,Ci,Co] (`stride2_by_phases_applies`), whose gradients are computed phase by phase (`_stride2_gradients`):
    XLA's CPU backend computes a strided convolution's input gradient as a convolution of the output gradient
    dilated with zeros, several times slower than a stride-1 convolution of the same arithmetic; split into phases,
    every gradient is a stride-1 convolution. The values are those of the plain op's gradients up to float rounding."""
    return _conv2d_stride2(tf.convert_to_tensor(x), tf.convert_to_tensor(kernel))  # values, not variables


@tf.custom_gradient
def _conv2d_stride2(x, kernel):
    def grad(dy):
        return _stride2_gradients(x, kernel, dy)

    return tf.nn.conv2d(x, kernel, 2, "SAME"), grad


def _stride2_gradients(x, kernel, dy):
    """(dx, dkernel) of `conv2d_stride2`. SAME padding of an even size with stride 2 pads one zero row (column) at the
    end, and output cell (i, j) reads x_pad[2i + kh, 2j + kw]. Phase (a, c) of x_pad, x_pad[2i + a, 2j + c], meets
    only the taps kh = a + 2m, kw = c + 2l (m, l in {0, 1}, kh, kw < 3): the output is the sum over the four phases of
    stride-1 VALID convolutions with those 2x2, 2x1, 1x2 and 1x1 sub-kernels, and each phase's gradients are those of
    its stride-1 convolution."""
    h, w, channels = x.shape[1], x.shape[2], x.shape[3]
    h2, w2 = h // 2, w // 2
    # Two zero rows and columns keep the padded size even; the second is never read.
    x_phases = tf.reshape(tf.pad(x, [[0, 0], [0, 2], [0, 2], [0, 0]]), [-1, h2 + 1, 2, w2 + 1, 2, channels])
    one = [1, 1, 1, 1]
    dx_rows, dkernel_parts = [], {}
    for a in (0, 1):
        dx_row = []
        for c in (0, 1):
            sub_kernel = kernel[a::2, c::2]  # [2 - a, 2 - c, Ci, Co]: the taps (a + 2m, c + 2l)
            rows, cols = h2 + 1 - a, w2 + 1 - c  # the phase's cells that some output cell reads
            phase = x_phases[:, :rows, a, :cols, c, :]
            d_phase = tf.raw_ops.Conv2DBackpropInput(input_sizes=tf.shape(phase), filter=sub_kernel,
                                                     out_backprop=dy, strides=one, padding="VALID")
            dkernel_parts[a, c] = tf.raw_ops.Conv2DBackpropFilter(input=phase, filter_sizes=tf.shape(sub_kernel),
                                                                  out_backprop=dy, strides=one, padding="VALID")
            dx_row.append(tf.pad(d_phase, [[0, 0], [0, a], [0, c], [0, 0]]))  # [B, h2 + 1, w2 + 1, Ci]
        dx_rows.append(tf.stack(dx_row, 3))  # [B, h2 + 1, w2 + 1, 2, Ci]: column phases interleaved
    dx_pad = tf.reshape(tf.stack(dx_rows, 2), [-1, h + 2, w + 2, channels])
    dkernel = tf.stack([tf.stack([dkernel_parts[kh % 2, kw % 2][kh // 2, kw // 2] for kw in range(3)])
                        for kh in range(3)])
    return dx_pad[:, :h, :w], dkernel


def composed_kernel(first, second):
    """The kernel of `conv(conv(x, first), second)` away from the grid's border: first [n, m, Ci, Cm] and second
    [k, l, Cm, Co] (stride 1) -> [n + k - 1, m + l - 1, Ci, Co]. Output cell p reads first's tap a of the cell that
    second's tap b reads, p + a + b (centred offsets), so the composed tap c sums first[a] @ second[b] over a + b = c:
    each of second's taps adds first's kernel, mapped to Co channels, placed at that tap's offset."""
    k, l = second.shape[0], second.shape[1]
    return tf.add_n([tf.pad(dense_last_axis(first, second[i, j]), [[i, k - 1 - i], [j, l - 1 - j], [0, 0], [0, 0]])
                     for i in range(k) for j in range(l)])


def conv2d_same_by_taps(x, kernel):
    """`tf.nn.conv2d(x, kernel, 1, "SAME")` for x [B,H,W,Ci] (static H, W) and an odd-sized kernel [n, m, Ci, Co] with
    few output channels, as one matrix product and shifted sums: every tap's kernel side by side, [Ci, n * m * Co],
    gives each cell its n * m taps' values; output cell (y, x) adds tap (i, j)'s value of cell (y + i - n // 2,
    x + j - m // 2) (zero outside the grid). A convolution to a few channels is a matrix product with a narrow
    output, which keeps little of the CPU's arithmetic busy; this one's product is n * m * Co wide, and its gradients
    are such products too, the shifted sums a fused pass over memory."""
    n, m, ci, co = kernel.shape
    h, w = x.shape[1], x.shape[2]
    values = dense_last_axis(x, tf.reshape(tf.transpose(kernel, [2, 0, 1, 3]), [ci, n * m * co]))
    shifted = []
    for i in range(n):
        for j in range(m):
            dy, dx = i - n // 2, j - m // 2  # the cell read, relative to the output cell
            tap = values[:, max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0), (i * m + j) * co:(i * m + j + 1) * co]
            shifted.append(tf.pad(tap, [[0, 0], [max(-dy, 0), max(dy, 0)], [max(-dx, 0), max(dx, 0)], [0, 0]]))
    return tf.add_n(shifted)


def conv_chain_same(x, kernels):
    """`conv(... conv(conv(x, k1), k2) ..., kn)` with SAME padding, stride 1, no bias and nothing between, for x
    [B,H,W,C] (static H, W) and square odd kernels: one convolution by the composed kernel (`composed_kernel`,
    `conv2d_same_by_taps`), the same values up to float rounding.

    The composed kernel alone is not the chain near the border: the chain pads each intermediate grid with zeros,
    while the composed kernel sees the intermediate values that the cells just outside the grid would have. That
    changes the output cells within `ring` = (sum of the radii but the first kernel's) of the border; those are
    computed by the chain itself, on the border strips of x that hold them (`ring` plus the total radius wide: a
    strip's cut edge changes only the cells within the total radius of it). A grid too small for the strips runs
    the chain as it is."""
    def chain(t):
        for k in kernels:
            t = tf.nn.conv2d(t, k, 1, "SAME")
        return t

    if len(kernels) == 1:
        return conv2d_same_by_taps(x, kernels[0])
    radii = [k.shape[0] // 2 for k in kernels]
    ring, strip = sum(radii[1:]), sum(radii[1:]) + sum(radii)
    h, w = x.shape[1], x.shape[2]
    if h < 2 * strip or w < 2 * strip:
        return chain(x)
    kernel = kernels[0]
    for k in kernels[1:]:
        kernel = composed_kernel(kernel, k)
    x, top, bottom, left, right = _border_strips(x, strip)
    inner = conv2d_same_by_taps(x, kernel)[:, ring:h - ring, ring:w - ring]
    top, bottom = chain(top)[:, :ring], chain(bottom)[:, strip - ring:]
    left, right = chain(left)[:, ring:h - ring, :ring], chain(right)[:, ring:h - ring, strip - ring:]
    return tf.concat([top, tf.concat([left, inner, right], 2), bottom], 1)


@tf.custom_gradient
def _border_strips(x, width):
    """x [B,H,W,C] -> (x, its first and last `width` rows, its first and last `width` columns). The gradient adds the
    strips' gradients into x's own in one pass (the slices' own gradients would each be a zero-filled grid of x's
    size, all alive at once)."""
    h, w = x.shape[1], x.shape[2]

    def grad(dx, d_top, d_bottom, d_left, d_right):
        bands = []
        for (r0, r1), d_rows in (((0, width), d_top), ((width, h - width), None), ((h - width, h), d_bottom)):
            band = dx[:, r0:r1]
            band = tf.concat([band[:, :, :width] + d_left[:, r0:r1], band[:, :, width:w - width],
                              band[:, :, w - width:] + d_right[:, r0:r1]], 2)
            bands.append(band if d_rows is None else band + d_rows)
        return tf.concat(bands, 1), None

    return (tf.identity(x), x[:, :width], x[:, h - width:], x[:, :, :width], x[:, :, w - width:]), grad


def _chunking(total, static_total, chunk_size):
    """(chunk, number of chunks) for `total` points (a tensor; `static_total` its value if known, else None): Python
    ints when the count is static or `chunk_size >= ONE_CHUNK` makes it one chunk, tensors otherwise."""
    if static_total is not None:
        chunk = max(min(chunk_size, static_total), 1)
        return chunk, max(-(-static_total // chunk), 1)
    if chunk_size >= ONE_CHUNK:  # one chunk of every point, however many there are (see ONE_CHUNK)
        return tf.maximum(total, 1), 1
    chunk = tf.maximum(tf.minimum(chunk_size, total), 1)
    return chunk, tf.maximum((total + chunk - 1) // chunk, 1)


def _over_chunks(num_chunks, body, state):
    """state = body(i, state) for each chunk i: inline for a static single chunk, else a tf.while_loop."""
    if isinstance(num_chunks, int) and num_chunks == 1:
        return body(0, state)
    return tf.while_loop(lambda i, _: i < num_chunks, lambda i, s: (i + 1, body(i, s)), (tf.constant(0), state),
                         maximum_iterations=num_chunks)[1]


def chunked_segment_sum(fn, points, point_valid, weights, segment_ids, num_segments, chunk_size):
    """Segment sums of per-point values that `fn` computes `chunk_size` points at a time, and optionally per-point
    rows beside them; with a gradient that recomputes each chunk.

    fn(points [P',D], point_valid [P'], weights) -> (values [P',C], rows [P',U] or None) for a chunk of P' points.
    points: [P,D] float (the flattened points); point_valid: [P] bool. Padded to whole chunks with zeros (False).
    weights: tensors that every chunk uses (e.g. kernels); their gradients are summed over the chunks.
    segment_ids: [P] int32, -1 for points in no segment.
    Returns (sums [num_segments, C], rows [P, U] or None).

    One chunk's intermediates exist at a time, forward and backward: the loop has a gradient of its own because the
    automatic one of a tf.while_loop keeps every chunk's intermediates in TensorLists, which may not leave an XLA
    program (the point stages' forward and backward are separate programs in compile mode "hybrid"). A static count
    of one chunk runs without a loop; more always run in a tf.while_loop, where XLA adds into the sums in place
    (unrolled, it reassociates the sums into extra grids). `chunk_size >= ONE_CHUNK` makes the count one chunk,
    static, at any point count.
    """
    total = tf.shape(segment_ids)[0]
    chunk, num_chunks = _chunking(total, segment_ids.shape[0], chunk_size)

    def to_chunks(t, fill):  # [P, ...] -> [K, chunk, ...]
        t = tf.pad(t, [[0, num_chunks * chunk - total]] + [[0, 0]] * (len(t.shape) - 1), constant_values=fill)
        return tf.reshape(t, tf.concat([[num_chunks, chunk], tf.shape(t)[1:]], 0))

    ids, valid = to_chunks(segment_ids, -1), to_chunks(point_valid, False)

    @tf.custom_gradient
    def run(points, *weights):  # points [K, chunk, D]
        weights = list(weights)

        def chunk_outputs(points, valid, ids):  # one chunk's segment sums and rows
            values, rows = fn(points, valid, weights)
            return tf.math.unsorted_segment_sum(values, ids, num_segments), rows

        def forward(i, state):
            sums, rows = chunk_outputs(points[i], valid[i], ids[i])
            return [state[0] + sums] + ([] if rows is None else [tf.tensor_scatter_nd_update(state[1], [[i]],
                                                                                             rows[None])])

        # An empty chunk gives the outputs' shapes: zero sums to add the chunks to, and the rows' width.
        sums, rows = chunk_outputs(points[0][:0], valid[0][:0], ids[0][:0])
        rows = [] if rows is None else [tf.zeros([num_chunks, chunk, rows.shape[-1]], rows.dtype)]
        state = _over_chunks(num_chunks, forward, [sums] + rows)

        def grad(d_sums, d_rows=None):
            def backward(i, state):
                d_points, d_weights = state
                chunk_points = points[i]
                with tf.GradientTape() as tape:
                    tape.watch([chunk_points] + weights)
                    values, rows = fn(chunk_points, valid[i], weights)
                # The segment sum's gradient, without recomputing the sum (its size may be no compile-time constant
                # in a separate backward program).
                gathered = tf.gather(d_sums, tf.maximum(ids[i], 0))
                d_values = tf.where(ids[i][:, None] >= 0, gathered, tf.zeros_like(gathered))
                d_chunk, *d_weights_chunk = tape.gradient(
                    [values] + ([] if rows is None else [rows]), [chunk_points] + weights,
                    output_gradients=[d_values] + ([] if rows is None else [d_rows[i]]),
                    unconnected_gradients=tf.UnconnectedGradients.ZERO)
                return (tf.tensor_scatter_nd_update(d_points, [[i]], d_chunk[None]),
                        [d + x for d, x in zip(d_weights, d_weights_chunk)])

            d_points, d_weights = _over_chunks(num_chunks, backward,
                                               (tf.zeros_like(points), [tf.zeros_like(w) for w in weights]))
            return [d_points] + d_weights

        return state, grad

    sums, *rows = run(to_chunks(points, tf.zeros([], points.dtype)), *weights)
    return sums, (tf.reshape(rows[0], [-1, rows[0].shape[-1]])[:total] if rows else None)


def _double_axis(x, axis):
    """Bilinear x2 along one spatial `axis` of x, half-pixel centres, edges clamped: output 2i samples input i - 1/4
    (0.75 x[i] + 0.25 x[i-1]) and output 2i+1 samples i + 1/4 (0.75 x[i] + 0.25 x[i+1]), x[-1] and x[n] read as the
    edge values, as `tf.image.resize(method="bilinear")` maps them."""
    def part(start, size):
        begin, sizes = [0] * len(x.shape), [-1] * len(x.shape)
        begin[axis], sizes[axis] = start, size
        return tf.slice(x, begin, sizes)

    shape = tf.shape(x)
    n = shape[axis]
    before = tf.concat([part(0, 1), part(0, n - 1)], axis)
    after = tf.concat([part(1, n - 1), part(n - 1, 1)], axis)
    pairs = tf.stack([0.75 * x + 0.25 * before, 0.75 * x + 0.25 * after], axis + 1)
    return tf.reshape(pairs, tf.concat([shape[:axis], [2 * n], shape[axis + 1:]], 0))


def bilinear_upsample_2x(x):
    """[B,H,W,C] -> [B,2H,2W,C]: the bilinear x2 upsampling of `tf.image.resize` (half-pixel centres, no antialias:
    Keras's bilinear `UpSampling2D`) as slices, weighted sums and an interleave, one spatial axis at a time; the
    values are the resize's to float rounding. XLA lowers the resize and its gradient (ResizeBilinearGrad) through
    temporaries of many times the input's size; these ops and their gradients need none beyond the tensors' own."""
    return _double_axis(_double_axis(x, 1), 2)

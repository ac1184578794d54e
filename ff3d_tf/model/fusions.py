"""How the sweeps of an example meet in FastFlow3D's U-Net (`model.temporal`), as units: each says how many branches
the U-Net encodes (stacked on the batch axis, with shared weights; the decoder concatenates their layers depth-wise),
what it feeds the U-Net from the sweeps' pillar grids, and which pillar grids a head's state reads
(`ff3d_tf.model.heads.Head.reads_pillar_grids`). A new fusion is one class here, its entry in `FUSIONS` and its name
in `ff3d_tf.config.TEMPORALS` (`tests/model/test_units.py` ties the two).

What the model (`m` below) asks of a fusion, in both forwards:
  `branches(num_frames)`: the U-Net's branches;
  `encode(m, grids, pillar_ids, point_valid, for_head)`: the sweeps' pillar sums (float32 [B,H,W,C] each, in slot
      order t0, tm1, ...; with each cloud's flat pillar ids and validity) -> (the U-Net's input in `m.conv_dtype`,
      [branches B,H,W,C], t0's branch first; what the head's grids need beyond it, a dict, when `for_head`);
  `head_grids(m, bev, extra)`: the pillar grids a head's state reads, [B,H,W,C] each (`head_grid_count` of them).
"""
from __future__ import annotations

import abc
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.model import ops


class Fusion(abc.ABC):
    """The interface (module docstring). `frames`: the numbers of sweeps it reads, (min, max)."""

    name = ""
    frames = (2, schema.MAX_NUM_FRAMES)

    @abc.abstractmethod
    def branches(self, num_frames: int) -> int:
        """Each unit's own (the module docstring)."""

    @abc.abstractmethod
    def head_grid_count(self, num_frames: int) -> int:
        """Each unit's own (the module docstring)."""

    @abc.abstractmethod
    def encode(self, m, grids, pillar_ids, point_valid, for_head: bool):
        """Each unit's own (the module docstring)."""

    @abc.abstractmethod
    def head_grids(self, m, bev, extra: dict) -> list:
        """Each unit's own (the module docstring)."""


class Stack(Fusion):
    """Every sweep through the shared U-Net encoder, the decoder's skips concatenating all of them, t0 first (the
    pair's concatenation extended to N sweeps); a head's state reads every sweep's pillar sums."""

    name = "stack"

    def branches(self, num_frames):
        return num_frames

    def head_grid_count(self, num_frames):
        return num_frames

    def encode(self, m, grids, pillar_ids, point_valid, for_head):
        return tf.cast(tf.concat(grids, 0), m.conv_dtype), {}

    def head_grids(self, m, bev, extra):
        return tf.split(bev, m.branches, axis=0)


class Pair(Stack):
    """The paper's two clouds (Sec. 4): `stack` of 2 sweeps."""

    name = "pair"
    frames = (2, 2)


class Delta(Fusion):
    """DeltaFlow's decayed difference (Zhang et al., NeurIPS 2025; KTH-RPL/OpenSceneFlow @848bf86
    `src/models/basic/sparse_encoder.py` lines 72-104) as the U-Net's only input, one branch whatever the number of
    sweeps: the newest sweep's grid F_new and the others' F_j ranked by recency (`m.slots_newest_first`, from the
    records' partner side), sum over j of decay^j (F_new - F_j), divided by N - 1.

    Each F is a sweep's pillar *means* of the point features (row B's sums over its point count; 0 in an empty
    pillar), as the authors' voxel features average their points (`DynamicPillarFeatureNet(mode='avg')`): an
    unchanged static pillar differs by nothing, whatever its point count does between sweeps. A head's state reads
    the t0 sweep's pillar means and the difference."""

    name = "delta"

    def branches(self, num_frames):
        return 1

    def head_grid_count(self, num_frames):
        return 2

    def newest_first(self, m) -> tuple[int, ...]:
        """The slots by recency, newest first (`schema.slots_newest_first` of the model's partner side)."""
        return m.slots_newest_first

    def encode(self, m, grids, pillar_ids, point_valid, for_head):
        means = [ops.pillar_means(g, ids, valid) for g, ids, valid in zip(grids, pillar_ids, point_valid)]
        newest, *older = self.newest_first(m)
        delta = tf.add_n([m.temporal_decay ** j * (means[newest] - means[slot]) for j, slot in enumerate(older)])
        bev = tf.cast(delta / (len(grids) - 1), m.conv_dtype)
        return bev, ({"grid_t0": tf.cast(means[0], m.conv_dtype)} if for_head else {})

    def head_grids(self, m, bev, extra):
        return [extra["grid_t0"], bev]


FUSIONS = {f.name: f for f in (Pair(), Stack(), Delta())}  # model.temporal -> its unit

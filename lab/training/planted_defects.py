"""Defects planted on purpose, so that a benchmark can prove it sees one (lab only: the product never imports this).

`delta_reversed` (`model.temporal=delta_reversed`): DeltaFlow's difference always taken from the t0 sweep, whatever
side of t0 the records' partner lies on, as the project computed it before it followed the authors' order
(`ff3d_tf.model.fusions.Delta`). On Argoverse 2 records (partner = the next sweep) it differences t0 against t+1 and
the history at once, so the history's terms point the other way; on WOD records it equals `delta`.

`run_tool(tool, argv)` runs one of the project's tools in this process with the planted variants registered beside
the product's, after the caller's start-up (`lab/tools/run_planted.py`: `_common.start`): the registration (which
imports TensorFlow), then the tool's `main()` with its start-up already done.
"""
from __future__ import annotations

import os
import runpy
import sys

REVERSED_DELTA = "delta_reversed"


def register() -> None:
    """Adds the planted fusions to the product's registry and to the config's names (`config.TEMPORALS`, read when a
    config is validated), for this process only."""
    from ff3d_tf import config
    from ff3d_tf.model import fusions

    class ReversedDelta(fusions.Delta):
        name = REVERSED_DELTA

        def newest_first(self, m):
            return tuple(range(m.num_frames))  # t0 as the reference whatever the partner side: the planted defect

    fusions.FUSIONS[REVERSED_DELTA] = ReversedDelta()
    if REVERSED_DELTA not in config.TEMPORALS:
        config.TEMPORALS = config.TEMPORALS + (REVERSED_DELTA,)


def run_tool(tool: str, argv: list[str]) -> None:
    """Runs `tool` (a path under tools/) as `python tool argv...` would, with `register` done first; the process's
    start-up (`_common.start`) is done already."""
    tools_dir = os.path.dirname(os.path.abspath(tool))
    if tools_dir not in sys.path:
        sys.path.insert(0, tools_dir)
    import _common
    register()
    _common.start = lambda _job: {}  # the tool's own start-up call: done above, before TensorFlow was imported
    sys.argv = [tool, *argv]
    runpy.run_path(tool, run_name="__main__")

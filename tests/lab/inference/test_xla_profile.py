"""The forward's variants (tools/export_xla.py --variants) compute the plain artifact's flow, and the profile
(lab/tools/profile_xla.py, run where TensorFlow cannot be imported) attributes the device's time to HLO instructions,
their kind and the paper table's rows."""
import json

import pytest

jax = pytest.importorskip("jax", reason="the xla extra (pip install .[xla]) provides jax")

from conftest import ROOT, tiny_model_off_initial_values  # noqa: E402
from no_tensorflow import run_without_tf  # noqa: E402
from ff3d_tf.inference.xla_export import check_variants, export_forward  # noqa: E402
from lab.inference import xla_profile  # noqa: E402

# A hand-written optimized module: a cuDNN convolution, a loop fusion of its BatchNorm and ReLU, a scatter fusion and
# a copy, with TensorFlow op names as XLA keeps them (row letter, Keras's _1 suffix, op).
HLO = """HloModule jit_call, entry_computation_layout={()->f32[]}

%fused_bn (param_0: bf16[1,8,8,4]) -> bf16[1,8,8,4] {
  %param_0 = bf16[1,8,8,4]{3,2,1,0} parameter(0)
  %mul.1 = bf16[1,8,8,4]{3,2,1,0} multiply(%param_0, %param_0), metadata={op_name="D_1/FusedBatchNormV3"}
  ROOT %max.1 = bf16[1,8,8,4]{3,2,1,0} maximum(%mul.1, %mul.1), metadata={op_name="D_1/Relu"}
}

%fused_scatter (p0: f32[64,4], p1: s32[10,1], p2: f32[10,4]) -> f32[64,4] {
  %p0 = f32[64,4]{1,0} parameter(0)
  %p1 = s32[10,1]{1,0} parameter(1)
  %p2 = f32[10,4]{1,0} parameter(2)
  ROOT %scatter.3 = f32[64,4]{1,0} scatter(%p0, %p1, %p2), to_apply=%add_f32
}

ENTRY %main (a: bf16[1,8,8,4], w: bf16[3,3,4,4]) -> f32[] {
  %a = bf16[1,8,8,4]{3,2,1,0} parameter(0)
  %cudnn-conv.7 = (bf16[1,8,8,4]{3,2,1,0}, u8[0]{0}) custom-call(%a, %w), custom_call_target="__cudnn$convForward", metadata={op_name="D_1/conv/convolution"}
  %loop_fusion.2 = bf16[1,8,8,4]{3,2,1,0} fusion(%gte), kind=kLoop, calls=%fused_bn
  %input_scatter_fusion = f32[64,4]{1,0} fusion(%z, %i, %u), kind=kInput, calls=%fused_scatter, metadata={op_name="A_1/UnsortedSegmentSum"}
  ROOT %copy.4 = f32[64,4]{0,1} copy(%input_scatter_fusion), metadata={op_name="Floor_2"}
}
"""


def test_instructions_get_their_kind_and_model_row():
    hlo = xla_profile.parse_hlo(HLO)
    got = {name: (xla_profile.category(hlo, name), xla_profile.model_row(hlo, name))
           for name in ("cudnn-conv.7", "loop_fusion.2", "input_scatter_fusion", "copy.4")}
    assert got == {"cudnn-conv.7": ("convolution", "D"),
                   "loop_fusion.2": ("elementwise", "D"),  # no op name of its own: its fused ops' row
                   "input_scatter_fusion": ("scatter", "A"),
                   "copy.4": ("copy", xla_profile.OTHER_ROW)}  # "Floor_2" is no model row
    assert xla_profile.category(hlo, "not-in-the-module") == "other"


def test_unknown_variants_are_refused():
    check_variants(["fold_bn", "fold_bn+one_chunk"])
    for bad in ("fold", "fold_bn+", ""):
        with pytest.raises(ValueError, match="variant"):
            check_variants([bad])


@pytest.fixture(scope="module")
def exported_variants(tiny_config, tmp_path_factory):
    out_dir = str(tmp_path_factory.mktemp("xla_variants"))
    export_forward(tiny_config, tiny_model_off_initial_values(tiny_config), [700], out_dir, precisions=("float32",),
                   variants=("fold_bn", "one_chunk"), log=lambda _: None)
    return out_dir


def test_profile_tool_without_tensorflow(exported_variants, tiny_config, tmp_path):
    out = tmp_path / "profile.json"
    run_without_tf(f"{ROOT}/lab/tools/profile_xla.py", exported_variants, "--points", "700", "--precision", "float32",
                   "--bake_weights", "--runs", "3", "--warmup", "1", "--trace_runs", "2", "--out", str(out))
    rows = {r["program"]: r for r in json.loads(out.read_text())["rows"]}
    assert list(rows) == ["plain", "plain, weights baked in", "fold_bn", "one_chunk"]
    assert rows["plain"]["flow_scale_mps"] > 1.0  # weights off their initial values: a real flow to compare
    # float32 throughout: the folded BatchNorm and the constant weights change rounding only.
    for name in ("plain, weights baked in", "fold_bn", "one_chunk"):
        assert rows[name]["max_abs_flow_diff_vs_plain_mps"] < 1e-4 * rows["plain"]["flow_scale_mps"], name
    for row in rows.values():
        p = row["profile"]
        assert p["source"] == "CPU thunks" and p["busy_ms"] > 0
        assert sum(p["by_category"].values()) == pytest.approx(p["busy_ms"])
        assert sum(p["by_row"].values()) == pytest.approx(p["busy_ms"])
        assert p["by_category"]["convolution"] > 0
    # Every convolution row of the tiny model (three stages of two ConvBlocks, C-H; Upsample-Skip S-U; V) and the
    # point encoder (A) has device time of its own in the plain program.
    rows_with_time = set(rows["plain"]["profile"]["by_row"])
    assert set("ACDEFGHSTUV") <= rows_with_time, rows_with_time

"""NSFP's per-pair optimiser as portable XLA programs (ff3d_tf.labels.nsfp_export, nsfp_program): a tiny export
(one 1024-point bucket, a 2 x 16 MLP, 5 steps a call, a 40 x 40 x 24 grid; float32 and tf32) run by JAX in a process
where TensorFlow cannot be imported equals TensorFlow's own grids (`build_distance_grid`) and fit
(`nsfp._fit_segment`); the lab's runner tool (lab/tools/run_nsfp_xla.py) times it and checks the saved reference
there; the reader imports no TensorFlow."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("jax", reason="the xla extra (pip install .[xla]) provides jax")

import tensorflow as tf  # noqa: E402

from conftest import ROOT  # noqa: E402
from no_tensorflow import run_without_tf  # noqa: E402
from ff3d_tf import xla_program  # noqa: E402
from ff3d_tf.labels import nsfp, nsfp_export, nsfp_program  # noqa: E402

OPTIONS = nsfp.NsfpOptions(hidden_layers=2, hidden_units=16, grid_cell_m=0.25, crop_xy_half_extent_m=4.0,
                           crop_z_range_m=(-3.0, 3.0), reverse_every=2)  # two-sided, as the pseudo-label job fits
POINTS, SEGMENT_STEPS, CALLS = 1000, 5, 2

# The JAX side: both grids and CALLS segments of the fit on the entry's pair, saved for the comparison.
RUN_FIT = """
import sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from ff3d_tf.labels import nsfp_program
export_dir, calls, out_path = sys.argv[2], int(sys.argv[3]), sys.argv[4]
manifest = nsfp_program.read_manifest(export_dir)
entry = manifest["entries"][0]
program = nsfp_program.CompiledNsfp(export_dir, manifest, entry, "float32")
start = nsfp_program.initial_state(entry, nsfp_program.load_initial_params(export_dir, manifest),
                                   nsfp_program.load_state_arrays(export_dir))
clouds = program.put(nsfp_program.padded_clouds(nsfp_program.entry_pair(entry), entry))
grids, state = program.fit(clouds, start, calls)
assert sys.modules.get("tensorflow") is None, "the runner imported tensorflow"
np.savez(out_path, grid_tm1=np.asarray(grids[0]), grid_t0=np.asarray(grids[1]),
         **{f"s{i:03d}": np.asarray(x) for i, x in enumerate(state)})
"""


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out_dir = str(tmp_path_factory.mktemp("nsfp_xla"))
    manifest = nsfp_export.export_nsfp(OPTIONS, [POINTS], out_dir, SEGMENT_STEPS, ("float32", "tf32"),
                                       reference_calls=1, log=lambda _: None)
    return out_dir, manifest


def test_manifest_describes_the_programs(exported):
    out_dir, manifest = exported
    (entry,) = manifest["entries"]
    assert (entry["points"], entry["padded_points"], entry["dims"]) == (POINTS, 1024, [40, 40, 24])
    assert sorted(os.listdir(out_dir)) == sorted([
        entry["grid_file"], entry["fit_files"]["float32"], entry["fit_files"]["tf32"], nsfp_program.MANIFEST_NAME,
        nsfp_program.PARAMS_NAME, nsfp_program.STATE_ARRAYS_NAME, nsfp_program.REFERENCE_NAME])
    fields = [leaf["field"] for leaf in entry["state"]]
    assert fields[0] == "step" and fields.count("params") == manifest["num_params"] == 12  # 2 MLPs x 3 layers x 2
    assert manifest["hyper"]["patience"] == nsfp_export.TIMING_STEP_CAP
    # float32: the MLPs' matmuls at HIGHEST precision (float32-exact on GPUs); tf32: DEFAULT (TF32 allowed)
    highest = {}
    for precision, name in entry["fit_files"].items():
        exported = xla_program.load_program(os.path.join(out_dir, name), len(entry["state"]) + 4 + 8 + 7,
                                            len(entry["state"]), "the fit's arguments")
        assert exported.platforms == ("cpu", "cuda")
        highest[precision] = exported.mlir_module().count("HIGHEST")
    assert highest["float32"] > 0 and highest["tf32"] == 0, highest


def test_programs_without_tensorflow_equal_tensorflow_fit(exported, tmp_path):
    out_dir, manifest = exported
    entry = manifest["entries"][0]
    script = tmp_path / "run_fit.py"
    script.write_text(RUN_FIT)
    run_without_tf(str(script), ROOT, out_dir, str(CALLS), str(tmp_path / "jax.npz"))
    got = np.load(tmp_path / "jax.npz")
    # TensorFlow's own: the grids of build_distance_grid and CALLS calls of nsfp._fit_segment from initial_fit_state.
    clouds = nsfp_program.padded_clouds(nsfp_program.entry_pair(entry), entry)
    grid_tm1, grid_t0 = nsfp_export.tf_grids(entry, clouds, OPTIONS)
    hyper = tuple(tf.constant(a) for a in nsfp_program.hyper_arrays(manifest["hyper"]))
    state = nsfp.initial_fit_state(OPTIONS, entry["padded_points"])
    for _ in range(CALLS):
        state = nsfp._fit_segment(state, tuple(tf.constant(c) for c in clouds), (grid_tm1, grid_t0), hyper,
                                  2 * (OPTIONS.hidden_layers + 1), False, OPTIONS.squared_chamfer, SEGMENT_STEPS,
                                  OPTIONS.reverse_every)
    np.testing.assert_allclose(got["grid_tm1"], grid_tm1.distance_m.numpy(), rtol=0, atol=1e-5)
    np.testing.assert_allclose(got["grid_t0"], grid_t0.distance_m.numpy(), rtol=0, atol=1e-5)
    flat = tf.nest.flatten(state)
    assert len(flat) == len(entry["state"])
    index = {f: nsfp_program.state_index(entry, f) for f in ("step", "best_loss", "best_motion")}
    assert int(got[f"s{index['step']:03d}"]) == int(state.step) == CALLS * SEGMENT_STEPS
    np.testing.assert_allclose(got[f"s{index['best_loss']:03d}"], state.best_loss.numpy(), rtol=1e-5)
    motion = state.best_motion.numpy()
    assert np.abs(motion[:POINTS]).max() > 1e-3  # the fit moved: a real motion to compare
    np.testing.assert_allclose(got[f"s{index['best_motion']:03d}"], motion, rtol=0, atol=1e-5)
    for i, (leaf, want) in enumerate(zip(entry["state"], flat)):  # every leaf, Adam's slots included
        np.testing.assert_allclose(got[f"s{i:03d}"], want.numpy(), rtol=1e-4, atol=1e-6, err_msg=leaf["field"])


def test_runner_tool_times_and_checks_the_reference_without_tensorflow(exported, tmp_path):
    out_dir, _ = exported
    out_json = tmp_path / "nsfp.json"
    stdout = run_without_tf(os.path.join(ROOT, "lab", "tools", "run_nsfp_xla.py"), out_dir, "--runs", "2",
                            "--pair_steps", "5", "--pair_runs", "1", "--precisions", "float32", "--out", str(out_json))
    assert "NSFP per-pair fit" in stdout
    (row,) = json.loads(out_json.read_text())["rows"]
    assert row["pair_steps"] == SEGMENT_STEPS and row["seconds_per_step"] > 0 and row["seconds_per_pair"] > 0
    check = row["reference"]
    assert check["steps"] == SEGMENT_STEPS
    assert check["max_abs_grid_diff_m"] < 1e-5 and check["best_loss_rel_diff"] < 1e-5
    assert check["max_abs_motion_diff_m"] < 1e-5


def test_reader_imports_no_tensorflow():
    code = ("import sys; import ff3d_tf.labels.nsfp_program, ff3d_tf.xla_program; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('tensorflow', 'keras')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"


def test_synthetic_pair_is_checked_against_the_export(exported):
    _, manifest = exported
    entry = dict(manifest["entries"][0])
    pair = nsfp_program.entry_pair(entry)
    moving = np.abs(pair["motion_m"]).sum(1) > 0
    assert moving.any() and not moving.all()
    np.testing.assert_allclose(pair["motion_m"][moving][0], nsfp_program.SYNTHETIC_OBJECT_MOTION_M)
    with pytest.raises(xla_program.ExportFormatError, match="differs from the exporter's"):
        nsfp_program.entry_pair({**entry, "pair_seed": entry["pair_seed"] + 1})


def test_export_refuses_exact_chamfer(tmp_path):
    with pytest.raises(ValueError, match="exact_chamfer"):
        nsfp_export.fit_program_fn(nsfp.NsfpOptions(exact_chamfer=True, hidden_layers=1, hidden_units=4), 1024, 1,
                                   65536)

"""The pseudo-label job over pair records: the output holds the NSFP flow beside the input's fields, and a run killed
between pairs resumes to the same bytes as an uninterrupted one."""
import os

import numpy as np
import pytest

from ff3d_tf.data import pair_records, pairs, write_records
from ff3d_tf.labels import nsfp, pseudo_records

OPTIONS = nsfp.NsfpOptions(max_iterations=20, patience=20, segment_iterations=10, grid_cell_m=0.5,
                           crop_xy_half_extent_m=40.0)


@pytest.fixture(scope="module")
def records(tiny_segment, tiny_config, tmp_path_factory):
    out = str(tmp_path_factory.mktemp("records"))
    manifest = write_records.wod_manifest(tiny_config)
    pair_records.write_manifest(out, manifest)
    write_records.write_segment(tiny_segment, out, tiny_config, manifest)
    return pairs.list_segment_files(out), manifest


def _label(records, out_dir):
    files, manifest = records
    out_manifest = pseudo_records.output_manifest(manifest)
    pair_records.write_manifest(out_dir, out_manifest)
    return pseudo_records.pseudo_label_file(files[0], out_dir, OPTIONS, manifest, out_manifest)


def _read(path, manifest):
    return [{k: v.numpy() for k, v in ex.items()} for ex in pair_records.records_dataset(path, manifest,
                                                                                         manifest.extras)]


def test_output_holds_the_nsfp_flow_beside_the_input(records, tmp_path):
    counts = _label(records, str(tmp_path))
    assert counts["pairs"] == counts["fitted_pairs"] == 3 and counts["pseudo_labelled_points"] > 0
    files, manifest = records
    out = str(tmp_path / os.path.basename(files[0]))
    out_manifest = pair_records.read_manifest(str(tmp_path))
    assert out_manifest.extras == ("flow_mps_pseudo_t0",)
    got, want = _read(out, out_manifest), _read(files[0], manifest)
    assert not os.path.exists(out + ".parts")
    for g, w in zip(got, want):
        for k in w:
            np.testing.assert_array_equal(g[k], w[k], err_msg=k)
        # The pseudo-labels are NSFP's fit of this pair (same options, same seed: deterministic).
        dt_s = (int(w["timestamp_ns_t0"]) - int(w["timestamp_ns_partner"])) * 1e-9
        fit = nsfp.nsfp_flow(w["points_xyz_t0"], w["points_xyz_tm1_in_t0"], dt_s, OPTIONS)
        np.testing.assert_array_equal(g["flow_mps_pseudo_t0"], np.where(fit.valid_t0[:, None], fit.flow_mps_t0, 0))
    assert _label(records, str(tmp_path)) == {"already_done": 1}


def test_a_killed_run_resumes_to_the_same_bytes(records, tmp_path, monkeypatch):
    whole, resumed = tmp_path / "whole", tmp_path / "resumed"
    _label(records, str(whole))
    calls = []
    real = pseudo_records.nsfp_flow

    def dies_on_the_second_pair(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(pseudo_records, "nsfp_flow", dies_on_the_second_pair)
        with pytest.raises(KeyboardInterrupt):
            _label(records, str(resumed))
    name = os.path.basename(records[0][0])
    assert not os.path.exists(resumed / name)  # no output file until every pair is done
    assert os.listdir(resumed / (name + ".parts")) == ["000000.npy"]
    counts = _label(records, str(resumed))
    assert counts["fitted_pairs"] == 2 and counts["pairs"] == 3
    assert (resumed / name).read_bytes() == (whole / name).read_bytes()

"""The pseudo-label job over pair records: the output holds the NSFP flow beside the input's fields, and a run killed
between pairs resumes to the same bytes as an uninterrupted one."""
import os

import numpy as np
import pytest

from ff3d_tf.data import pair_records, pairs, write_records
from ff3d_tf.labels import nsfp, pseudo_records

# Few steps of a small MLP on the points within 8 m (a few thousand a pair, one point bucket): the job's bookkeeping,
# not the fit, is tested here (NSFP's 8 x 128 MLP only made its one compile slower).
OPTIONS = nsfp.NsfpOptions(max_iterations=8, patience=8, segment_iterations=4, grid_cell_m=0.5,
                           crop_xy_half_extent_m=8.0, hidden_layers=2, hidden_units=32)


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


def _with_a_bad_record(records, tmp_path):
    """A copy of the records file (and manifest) whose second record is not a pair record."""
    import tensorflow as tf
    files, manifest = records
    bad_dir = tmp_path / "bad_in"
    pair_records.write_manifest(str(bad_dir), manifest)
    path = str(bad_dir / os.path.basename(files[0]))
    good = [r.numpy() for r in tf.data.TFRecordDataset(files[0])]
    with tf.io.TFRecordWriter(path) as writer:
        for i, record in enumerate(good):
            writer.write(b"not a pair record" if i == 1 else record)
    return path, manifest


def test_a_bad_record_is_named_or_skipped(records, tmp_path):
    from ff3d_tf.data.wod_errors import FrameDecodeError
    path, manifest = _with_a_bad_record(records, tmp_path)
    out_manifest = pseudo_records.output_manifest(manifest)
    out = tmp_path / "out"
    pair_records.write_manifest(str(out), out_manifest)
    with pytest.raises(FrameDecodeError, match=r"record 1: field record: not a pair record") as err:
        pseudo_records.pseudo_label_file(path, str(out), OPTIONS, manifest, out_manifest)
    assert err.value.path == path and err.value.record_index == 1
    assert not os.path.exists(out / os.path.basename(path))
    counts = pseudo_records.pseudo_label_file(path, str(out), OPTIONS, manifest, out_manifest, skip_bad_records=True)
    assert counts["skipped_records"] == 1 and counts["pairs"] == 2
    assert counts["fitted_pairs"] == 1  # pair 0 was kept from the failed run; pair 2 is fitted now
    got = _read(str(out / os.path.basename(path)), pair_records.read_manifest(str(out)))
    want = _read(records[0][0], manifest)
    assert [int(g["timestamp_ns_t0"]) for g in got] == [int(want[i]["timestamp_ns_t0"]) for i in (0, 2)]

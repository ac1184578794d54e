"""Study definitions, the report table (with its relative change row) and the plots."""
import json

import pytest

from ff3d_tf.training import studies


def test_variants():
    ds = studies.variants("data_size", 10, (0.1, 0.25, 0.26, 1.0))
    # ceil(0.25 * 10) = ceil(0.26 * 10) = 3: one variant; data size changes training only.
    assert [(v.name, v.x) for v in ds] == [("segments_1", 0.1), ("segments_3", 0.3), ("segments_10", 1.0)]
    assert ds[1].train_changes == {"data.max_training_segments": 3} and not ds[1].input_changes
    dens = studies.variants("point_density", 10)
    assert [v.input_changes["data.point_keep_fraction"] for v in dens] == [0.1, 0.25, 0.5, 1.0]
    abl = studies.variants("class_ablation", 4)
    assert abl[0].name == "supervised" and len(abl) == 5
    assert all(not v.input_changes for v in abl)  # evaluated on the original labels
    ego = studies.variants("ego_motion", 4)
    assert ego[1].input_changes == {"data.ego_motion_compensation": False}
    with pytest.raises(ValueError, match="unknown study"):
        studies.variants("nope", 4)
    with pytest.raises(ValueError, match="shares"):
        studies.variants("point_density", 4, (0.0, 2.0))


def test_report(tmp_path):
    base = {"all/moving/mean_l2_mps": 1.0, "all/stationary/mean_l2_mps": 0.2, "vehicle/moving/mean_l2_mps": 2.0}
    worse = {"all/moving/mean_l2_mps": 2.59, "all/stationary/mean_l2_mps": 0.262, "vehicle/moving/mean_l2_mps": 2.0}
    rows = [{"variant": "with_ground", "x": None, "changes": {}, "metrics": base},
            {"variant": "ground_removed", "x": None, "changes": {"data.remove_ground_below_z_m": 0.2},
             "metrics": worse}]
    table = studies.markdown_table("ground_removal", rows)
    last = table.splitlines()[-1].split(" | ")
    assert last[0] == "| change vs with_ground" and last[1:3] == ["+159%", "+31%"]  # the paper's reported change
    assert "n/a" in table  # metrics absent from the rows (e.g. pedestrians) are marked, not invented
    paths = studies.write_report("ground_removal", rows, str(tmp_path))
    assert json.loads(open(paths["json"]).read())["variants"][1]["metrics"] == worse
    dens = [{"variant": f"points_{x}", "x": x, "changes": {},
             "metrics": {f"{c}/moving/frac_l2_le_{t}": x * 0.9 for c in studies.CLASSES for t in ("0.1", "1.0")}}
            for x in (0.1, 0.5, 1.0)]
    for study, r in (("ground_removal", rows), ("point_density", dens)):
        png = studies.plot(study, r, str(tmp_path / f"{study}.png"))
        assert open(png, "rb").read(8) == b"\x89PNG\r\n\x1a\n"

"""lab/labels/nsfp_timing.py: the table of an NSFP export's timing run. (Timing real programs:
tests/labels/test_nsfp_export.py runs lab/tools/run_nsfp_xla.py on an export.)"""
from lab.labels import nsfp_timing


def test_table_judges_the_target_on_both_fitted_counts():
    """A 150K pair fitted on every point is the 150,000-point entry; as the pseudo-label job fits it (one point in
    4), the 37,500-point entry. Both are judged against 1 s per pair; other sizes are only listed."""
    def row(points, seconds_per_pair):
        return {"points": points, "precision": "float32", "seconds_per_step": 1e-3, "grid_build_s_one_cloud": 0.01,
                "seconds_per_pair": seconds_per_pair, "pair_steps": 500, "reference": {}}
    result = {"device": "test", "platform": "cpu", "jax": "x", "job_fit_every": 4, "skipped": [],
              "rows": [row(150000, 1.5), row(37500, 0.6), row(64000, 0.2)]}
    table = nsfp_timing.nsfp_table(result)
    assert "150,000 points (every point fitted: 150,000; float32, 500 steps): not met" in table
    assert "(one point in 4 fitted, as the pseudo-label job does: 37,500; float32, 500 steps): met" in table
    assert table.count("Target <=") == 2
    # s at 1000 steps = both grids + 1000 steps: 2 * 0.01 + 1000 * 1e-3 = 1.02
    assert "| 64,000 | float32 | 1.00 | 10.0 | 0.200 at 500 steps | 1.02 | 5.02 |" in table
    assert "one point in" not in nsfp_timing.nsfp_table({**result, "job_fit_every": 1})

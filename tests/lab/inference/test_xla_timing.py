"""lab/inference/xla_timing.py: the forward's latency table beside the paper's P100 figures. (Timing real artifacts:
tests/training/test_xla_step.py runs lab/tools/run_xla.py on an export.)"""
from lab.inference import xla_timing


def test_latency_table_beside_the_paper():
    result = {"device": "H200", "platform": "gpu", "jax": "0.11.2", "skipped": [],
              "latency": [{"points": 32000, "precision": "float32", "median_ms": 4.0, "mean_ms": 4.1, "min_ms": 3.9,
                           "median_host_ms": 5.0},
                          {"points": 1000000, "precision": "tf32", "median_ms": 12.5, "mean_ms": 12.6,
                           "min_ms": 12.0, "median_host_ms": 15.0},
                          {"points": 5000, "precision": "float32", "median_ms": 1.0, "mean_ms": 1.0, "min_ms": 1.0,
                           "median_host_ms": 1.0}]}
    rows = xla_timing.latency_table(result).splitlines()[4:]
    # 49.3 / 4.0 = 12.3x (target 10x met); 98.1 / 12.5 = 7.8x (not met); 5,000 points: no paper figure.
    assert rows[0] == "| 32,000 | float32 | 4.00 | 4.10 | 3.90 | 5.00 | 49.3 | 12.3x | yes |"
    assert rows[1] == "| 1,000,000 | tf32 | 12.50 | 12.60 | 12.00 | 15.00 | 98.1 | 7.8x | no |"
    assert rows[2].endswith("| - | - | - |")

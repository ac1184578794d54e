"""lab.training.bench_input on Argoverse 2: labels made in the input pipeline against the records job and the
training input reading its records, in a process pinned to the cores asked."""
import os

from conftest import TINY_OVERRIDES

from lab.training import bench_input

FIRST_CPU = sorted(os.sched_getaffinity(0))[:1]
BATCH = 2  # TINY_OVERRIDES' train.global_batch_size


def test_av2_labels_in_the_pipeline_against_records_on_the_cores_asked():
    result = bench_input.av2_input_benchmark(None, TINY_OVERRIDES, [1], "ff3d_tf.labels.av2", logs=1, sweeps=4,
                                             points_per_sweep=2000, batches=1, progress=lambda line: None)
    run = result["runs"]["1"]
    assert run["cpus"] == FIRST_CPU
    assert result["pairs"] == 3 and result["points_per_sweep"] > 1000
    assert run["write_exact"]["timed"] == run["write_compact"]["timed"] == 3  # every pair of the log written
    assert run["labels_in_pipeline"]["timed"] == 2 * 3 and run["records_compact"]["timed"] == BATCH
    rates = result["per_core_per_s"]["1"]
    assert set(rates) == {"labels_in_pipeline", "write_exact", "write_compact", "records_exact", "records_compact"}
    assert all(v > 0 for v in rates.values())
    assert 0 < result["bytes_per_pair"]["compact"] < result["bytes_per_pair"]["exact"]
    assert result["records_over_labels_in_pipeline"]["1"]["exact"] == rates["records_exact"] / rates[
        "labels_in_pipeline"]

"""lab.bench: timer statistics, the round robin's order, this process's readings and the one benchmark cloud."""
import functools
import math
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT
from ff3d_tf import cpu, xla_export_dir
from ff3d_tf.inference import xla_artifact
from ff3d_tf.training import xla_step_runner
from ff3d_tf.schema import MODEL_INPUT_KEYS
from lab import bench, children, xla_export_timing
from lab.inference import xla_timing
from lab.labels import nsfp_timing
from lab.training import xla_step_timing


class FakeClock:
    """A clock that moves only when a measured call says so."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now

    def call_taking(self, seconds):
        def fn():
            self.now += seconds
        return fn


def test_timer_statistics_on_a_fake_clock():
    clock = FakeClock()
    durations = iter([9.0, 0.004, 0.001, 0.003, 0.010])  # the first call is the warm-up

    def fn():
        clock.now += next(durations)
    readings = bench.measure(fn, runs=4, warmup=1, reading=functools.partial(bench.timed, clock=clock))
    ms = [r["ms"] for r in readings]
    np.testing.assert_allclose(ms, [4.0, 1.0, 3.0, 10.0])
    s = bench.summary(ms)
    assert list(s) == ["median_ms", "mean_ms", "min_ms"]
    np.testing.assert_allclose([s["median_ms"], s["mean_ms"], s["min_ms"]], [3.5, 4.5, 1.0])
    assert bench.summary(ms, ("median",)) == {"median_ms": pytest.approx(3.5)}
    assert bench.middle(ms) == pytest.approx(4.0) and bench.middle([3.0, 1.0, 2.0]) == 2.0  # a measured value
    assert bench.elapsed(clock.call_taking(0.25), clock) == (None, 0.25)


def test_round_robin_interleaves_after_the_warm_up():
    order = []
    calls = {name: (lambda name=name: order.append(name)) for name in ("a", "b", "c")}
    readings = bench.round_robin(calls, runs=2, warmup=1)
    assert order == ["a", "b", "c"] * 3  # one warm-up round, then two measured rounds
    assert list(readings) == ["a", "b", "c"] and all(len(r) == 2 and r[0]["ms"] >= 0 for r in readings.values())
    assert len(bench.measure(lambda: None, runs=3)) == 3


class FakeTensor:
    """Copied to the host by np.asarray, like an eager tensor."""

    def __init__(self, value):
        self.value, self.copied = value, False

    def __array__(self, dtype=None, copy=None):
        self.copied = True
        return np.asarray(self.value, dtype)


def test_fetch_copies_nested_results_to_the_host():
    flow, valid = FakeTensor([1.0, 2.0]), FakeTensor(True)
    out = bench.fetched(lambda: {"flow_mps": flow, "more": [(valid, None)]})()
    assert flow.copied and valid.copied and isinstance(out["more"][0], tuple) and out["more"][0][1] is None
    np.testing.assert_array_equal(out["flow_mps"], [1.0, 2.0])


def test_readings_of_this_process():
    rss, peak, threads = (bench.proc_status(f) for f in ("VmRSS", "VmHWM", "Threads"))
    assert 0.01 < rss <= peak and isinstance(threads, int) and threads >= 1
    assert bench.reset_peak_rss(trim=True)  # Linux >= 4.0
    assert bench.proc_status("VmHWM") < peak + 0.01
    # The trim above gives freed heap back, so the resident set is read again, around the smaps read.
    rss_before = bench.proc_status("VmRSS")
    kinds = bench.smaps_by_kind()
    rss_after = bench.proc_status("VmRSS")
    low, high = sorted((rss_before, rss_after))
    assert low * 0.95 - 0.01 < sum(kinds.values()) < high * 1.05 + 0.01  # the kinds add up to the resident set
    assert kinds["file_other"] > 0 and kinds.get("file_tensorflow", 0) > 0  # the interpreter; TF's .so (conftest)
    rollup = bench.smaps_rollup()
    assert rollup["Rss"] > 0 and rollup["Anonymous"] > 0
    info = bench.mallinfo2()
    assert info is not None and info["uordblks"] > 0 and info["hblks"] >= 0  # glibc >= 2.33
    assert cpu.malloc_trim()
    load = bench.load_average()
    assert len(load) == 3 and all(float(v) >= 0 for v in load)


def test_readings_of_missing_files_are_explicitly_empty(tmp_path):
    missing = str(tmp_path / "no_such_dir" / "file")  # neither readable nor writable
    assert math.isnan(bench.proc_status("VmRSS", missing)) and math.isnan(bench.proc_status("NoSuchField"))
    assert bench.smaps_by_kind(missing) == {} and bench.smaps_rollup(missing) == {}
    assert bench.load_average(missing) == [] and bench.reset_peak_rss(path=missing) is False


def test_readings_of_one_call():
    memory = bench.timed_with_memory(lambda: np.ones(10_000_000).sum())  # 80 MB for the call
    assert set(memory) == {"ms", "rss_before_gb", "peak_rss_gb", "rss_after_gb", "peak_reset"}
    assert memory["peak_reset"] and memory["peak_rss_gb"] >= memory["rss_before_gb"] + 0.05
    usage = bench.timed_with_usage(lambda: sum(range(2_000_000)), trim=True)
    assert set(usage) == {"ms", "cpu_ms", "sys_ms", "minor_faults", "rss_after_gb", "peak_rss_gb", "peak_reset"}
    assert usage["ms"] > 0 and usage["cpu_ms"] > 0 and usage["minor_faults"] >= 0


BOUNDS = ((-40.0, 40.0), (-20.0, 30.0), (-3.0, 3.0))


def test_cloud_is_the_models_input_padded_and_inside_the_grid():
    clouds = bench.random_clouds(np.random.default_rng(0), 700, 1024, BOUNDS, batch_size=2)
    assert tuple(clouds) == MODEL_INPUT_KEYS
    for t in ("t0", "tm1"):
        xyz = clouds["points_xyz_t0" if t == "t0" else "points_xyz_tm1_in_t0"]
        features, mask = clouds[f"point_features_{t}"], clouds[f"point_mask_{t}"]
        assert (xyz.shape, xyz.dtype, features.shape, features.dtype) == ((2, 1024, 3), np.float32, (2, 1024, 2),
                                                                          np.float32)
        assert mask.dtype == bool and mask[:, :700].all() and not mask[:, 700:].any()
        assert not xyz[:, 700:].any() and not features[:, 700:].any()  # padding zero
        for axis, (lo, hi) in enumerate(BOUNDS):
            assert lo <= xyz[:, :700, axis].min() and xyz[:, :700, axis].max() < hi
            assert xyz[:, :700, axis].max() - xyz[:, :700, axis].min() > 0.9 * (hi - lo)  # spread over the grid
        assert 0 <= features[:, :700].min() and features[:, :700].max() < 1
    assert not np.array_equal(clouds["points_xyz_t0"], clouds["points_xyz_tm1_in_t0"])
    with pytest.raises(ValueError, match="points=2000"):
        bench.random_clouds(np.random.default_rng(0), 2000, 1024, BOUNDS)


def test_labels_cover_the_real_points_only():
    labels = bench.random_labels(np.random.default_rng(0), 700, 1024, batch_size=2)
    flow, class_id = labels["flow_mps_t0"], labels["class_id_t0"]
    assert (flow.shape, flow.dtype, class_id.shape, class_id.dtype) == ((2, 1024, 3), np.float32, (2, 1024), np.int32)
    assert not flow[:, 700:].any() and (class_id[:, 700:] == -1).all()
    assert -10 <= flow.min() and flow.max() <= 10 and set(np.unique(class_id[:, :700])) == {-1, 0, 1, 2, 3, 4}


def test_cloud_is_determined_by_the_seed():
    def make(seed):
        rng = np.random.default_rng(seed)
        return {**bench.random_clouds(rng, 300, 512, BOUNDS), **bench.random_labels(rng, 300, 512)}
    a, b, c = make(5), make(5), make(6)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not np.array_equal(a["points_xyz_t0"], c["points_xyz_t0"])


def test_the_tensorflow_example_and_the_xla_runners_inputs_are_this_cloud(tiny_config):
    from lab.training import bench_steps
    g = tiny_config.grid
    bounds = (g.x_range_m, g.y_range_m, g.z_range_m)
    rng = np.random.default_rng(3)
    want = bench.random_clouds(rng, 700, 1024, bounds)
    want.update(bench.random_labels(rng, 700, 1024))
    example, padded = bench_steps.example(tiny_config, np.random.default_rng(3), 700, labels=True)
    assert padded == 1024 and list(example) == list(want)
    for k, v in want.items():
        np.testing.assert_array_equal(example[k].numpy(), v, err_msg=k)
    manifest = {"grid": {"x_range_m": list(g.x_range_m), "y_range_m": list(g.y_range_m),
                         "z_range_m": list(g.z_range_m)}, "input_keys": list(MODEL_INPUT_KEYS)}
    entry = {"points": 700, "padded_points": 1024, "batch_size": 1}
    got = xla_export_dir.random_inputs(manifest, entry, np.random.default_rng(3))
    for k, v in zip(MODEL_INPUT_KEYS, got):
        np.testing.assert_array_equal(v, want[k], err_msg=k)


def test_bench_imports_no_tensorflow():
    # The modules are imported above too, so that the BUILD checker sees them as this test's dependencies.
    modules = ", ".join(m.__name__ for m in (bench, children, xla_artifact, xla_timing, xla_step_runner, xla_export_dir,
                                             xla_export_timing, xla_step_timing, nsfp_timing))
    script = ("import sys\nfor name in ('tensorflow', 'keras', 'jax'):\n    sys.modules[name] = None\n"
              f"sys.path.insert(0, {ROOT!r})\nimport {modules}\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]

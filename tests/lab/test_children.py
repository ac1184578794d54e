"""lab.children: a measurement in a fresh process gets its environment, its cores and a clear error."""
import os

import pytest

from lab import children


def test_child_gets_its_environment_and_cores():
    cpus = sorted(os.sched_getaffinity(0))
    got = children.run_child("lab.children:placement", cores=1, env={"TF_NUM_INTRAOP_THREADS": "3"})
    # pinned to this process's first CPU; the pools sized to one core, except where `env` says otherwise
    assert got == {"cpus": cpus[:1], "tf_threads": {"TF_NUM_INTEROP_THREADS": "1", "TF_NUM_INTRAOP_THREADS": "3"}}
    assert children.run_child("lab.children:placement")["cpus"] == cpus


def test_kwargs_reach_the_function():
    # ff3d_tf.cpu.describe reads the ISA caps from the child's environment
    got = children.run_child("ff3d_tf.cpu:describe", env={"ONEDNN_MAX_CPU_ISA": "AVX2"})
    assert got["limits"]["onednn_max_isa"] == "AVX2" and "avx512f" not in got["usable_flags"]


def test_a_failing_child_is_named_with_its_output():
    with pytest.raises(children.ChildError, match=r"(?s)pinning: its process ended with exit 1.*cores asked"):
        children.run_child("lab.children:pin_cores", {"cores": 10_000}, what="pinning")
    recorded = children.run_child("lab.children:pin_cores", {"cores": 10_000}, on_error="record")
    assert set(recorded) == {"error"} and "cores asked" in recorded["error"]


def test_a_child_past_its_time_is_stopped():
    # a Python start alone takes longer than a millisecond
    with pytest.raises(children.ChildError, match="still running after 0.001 s"):
        children.run_child("lab.children:placement", timeout_s=0.001)


def test_only_functions_of_the_lab_and_the_package_run():
    for bad in ("os:system", "ff3d_tf.cpu", "ff3d_tf_other.x:y", "ff3d_tf.cpu:", "lab.children", "laboratory.x:y"):
        with pytest.raises(ValueError, match="expected 'lab.module:name' or 'ff3d_tf.module:name'"):
            children.run_child(bad)

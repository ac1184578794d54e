"""The fuzzers' report and watchdog: outcomes by kind, the `slow` bound, and a hang aborting the process only when the
fuzz function is given `hang_s` (an argument; no module state sets it)."""
import ast
import inspect
import os
import subprocess
import sys
import time

from ff3d_tf.fuzz import av2, config, report, wod

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
FUZZ_DIR = os.path.join(ROOT, "ff3d_tf", "fuzz")


def test_judge_records_outcome_bound_and_detail():
    rep = report.Report()
    report.judge(rep, "a", "damaged x", lambda: ("named_error", "file: field x"), None)
    report.judge(rep, "a", "damaged y", lambda: (time.sleep(0.02), ("decoded", "3 points"))[1], None, bound_s=0.001)
    report.judge(rep, "b", "damaged z", lambda: (time.sleep(0.02), ("crash", "boom"))[1], None, bound_s=None)
    assert [(r.kind, r.outcome) for r in rep.results] == [("a", "named_error"), ("a", "slow"), ("b", "crash")]
    assert rep.results[0].detail == "damaged x -> file: field x"
    assert rep.table() == {"a": {"named_error": 1, "slow": 1}, "b": {"crash": 1}}
    assert [r.outcome for r in rep.defects] == ["slow", "crash"]
    assert rep.slowest().seconds >= 0.02
    text = rep.format("run")
    assert text.startswith("run: 3 inputs") and "DEFECT b -> crash: damaged z -> boom" in text


HANG = """if True:
    import sys, time
    from ff3d_tf.fuzz import config
    sleep_s, after_s = float(sys.argv[1]), float(sys.argv[3])
    hang_s = None if sys.argv[2] == "none" else float(sys.argv[2])
    def hanging_classify(text, dotted, path):
        time.sleep(sleep_s)
        return "decoded", "accepted"
    config.classify = hanging_classify
    rep = config.fuzz_configs(sys.argv[4], 1, hang_s=hang_s)
    time.sleep(after_s)
    print("finished", rep.results[0].outcome)
"""


def _fuzz_one_config(tmp_path, sleep_s: float, hang_s: str, after_s: float = 0.0) -> subprocess.CompletedProcess:
    """A real fuzz function whose one input takes `sleep_s` (a fake slow classification), in a fresh process."""
    env = dict(os.environ, PYTHONPATH=ROOT, TF_CPP_MIN_LOG_LEVEL="2")
    return subprocess.run([sys.executable, "-c", HANG, str(sleep_s), hang_s, str(after_s), str(tmp_path)], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=300)


def test_hang_s_aborts_a_hanging_input_with_its_traceback(tmp_path):
    start = time.perf_counter()
    hung = _fuzz_one_config(tmp_path, 120, "1.5")
    assert hung.returncode != 0 and time.perf_counter() - start < 100
    assert "Timeout" in hung.stderr and "hanging_classify" in hung.stderr, hung.stderr[-2000:]
    assert "finished" not in hung.stdout


def test_without_hang_s_a_slow_input_runs_to_its_end(tmp_path):
    done = _fuzz_one_config(tmp_path, 2.0, "none")
    assert done.returncode == 0 and "finished decoded" in done.stdout, done.stderr[-2000:]
    # A watchdog that did not fire is cancelled: nothing aborts the process after the input.
    done = _fuzz_one_config(tmp_path, 0.1, "1.5", after_s=2.5)
    assert done.returncode == 0 and "finished decoded" in done.stdout, done.stderr[-2000:]


def test_no_module_state_sets_the_watchdog():
    # Every fuzz function takes the watchdog bound as `hang_s` (default: none) ...
    for fuzz in (wod.fuzz_records, wod.fuzz_files, av2.fuzz_log, config.fuzz_configs):
        assert inspect.signature(fuzz).parameters["hang_s"].default is None, fuzz.__name__
    # ... and nothing in the package keeps it: no `global` statement, no module-level name of a watchdog or hang.
    for name in sorted(os.listdir(FUZZ_DIR)):
        if not name.endswith(".py"):
            continue
        with open(os.path.join(FUZZ_DIR, name), encoding="utf-8") as f:
            tree = ast.parse(f.read())
        assert not [n for n in ast.walk(tree) if isinstance(n, ast.Global)], name
        assigned = {t.id for n in tree.body if isinstance(n, (ast.Assign, ast.AnnAssign))
                    for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
        assert not {a for a in assigned if "watchdog" in a.lower() or "hang" in a.lower()}, name

"""The stage runner of the resumable jobs (`ff3d_tf.stages`): which stage is skipped, what is removed, what it says."""
import json
import os
import sys

import pytest

from ff3d_tf import stages as S


def _writer(output, marker, text="x"):
    """Arguments of a stage (a Python one-liner) that writes `output`/out.txt and appends `text` to `marker`."""
    code = (f"import os; os.makedirs({str(output)!r}, exist_ok=True); "
            f"open(os.path.join({str(output)!r}, 'out.txt'), 'w').write('done'); open({str(marker)!r}, 'a').write("
            f"{text!r})")
    return ["-c", code]


def _job(tmp_path, plan=("a", "b"), code="code-1", lines=None):
    return S.Stages(str(tmp_path / "stages"), plan, code=code, log=(lines.append if lines is not None else None))


def test_listing_of_a_file_and_of_a_folder(tmp_path):
    (tmp_path / "d" / "sub").mkdir(parents=True)
    (tmp_path / "d" / "sub" / "x.bin").write_bytes(b"123")
    (tmp_path / "d" / "y").write_bytes(b"")
    assert S.listing(str(tmp_path / "d")) == {os.path.join("sub", "x.bin"): 3, "y": 0}
    assert S.listing(str(tmp_path / "d" / "sub" / "x.bin")) == {"": 3}


def test_code_fingerprint_follows_names_and_contents(tmp_path):
    (tmp_path / "tools").mkdir()
    (tmp_path / "tools" / "t.py").write_text("a = 1\n")
    first = S.code_fingerprint(str(tmp_path))
    assert len(first) == 64 and S.code_fingerprint(str(tmp_path)) == first
    (tmp_path / "tools" / "t.py").write_text("a = 2\n")
    assert S.code_fingerprint(str(tmp_path)) != first
    (tmp_path / "tools" / "t.py").rename(tmp_path / "tools" / "u.py")
    assert len({first, S.code_fingerprint(str(tmp_path))}) == 2


def test_a_stage_whose_output_changed_reruns_and_every_later_stage_too(tmp_path):
    out_a, out_b, marker = tmp_path / "out_a", tmp_path / "out_b", tmp_path / "runs.txt"
    job = _job(tmp_path)
    assert job.run("a", _writer(out_a, marker, "a"), [str(out_a)]) and job.run("b", _writer(out_b, marker, "b"),
                                                                               [str(out_b)])
    record = json.loads((tmp_path / "stages" / "a.json").read_text())
    assert record["command"] == _writer(out_a, marker, "a") and record["code"] == "code-1"
    assert record["outputs"] == {str(out_a): {"out.txt": 4}} and record["seconds"] > 0

    job = _job(tmp_path)
    assert not job.run("a", _writer(out_a, marker, "a"), [str(out_a)])
    assert not job.run("b", _writer(out_b, marker, "b"), [str(out_b)])
    assert job.skipped == ["a", "b"] and set(job.seconds) == {"a", "b"} and marker.read_text() == "ab"

    # An output edited by hand: stage a runs again (over what is there: same command and code, nothing removed), and
    # b after it although its own record still matches.
    (out_a / "extra").write_text("")
    job = _job(tmp_path)
    assert job.run("a", _writer(out_a, marker, "a"), [str(out_a)])
    assert (out_a / "extra").exists()
    assert job.run("b", _writer(out_b, marker, "b"), [str(out_b)])
    assert job.skipped == [] and marker.read_text() == "abab"
    # An output removed: the same.
    (out_b / "out.txt").unlink()
    job = _job(tmp_path)
    assert not job.run("a", _writer(out_a, marker, "a"), [str(out_a)])
    assert job.run("b", _writer(out_b, marker, "b"), [str(out_b)]) and marker.read_text() == "ababb"


def test_a_stopped_stage_names_itself_and_resumes_over_its_outputs(tmp_path):
    output, marker = tmp_path / "out", tmp_path / "found.txt"
    # Notes whether its output was there when it started, writes some of it, stops with status 3.
    failing = ["-c", f"import os; part = os.path.join({str(output)!r}, 'part'); "
                     f"open({str(marker)!r}, 'a').write(str(int(os.path.exists(part)))); "
                     f"os.makedirs({str(output)!r}, exist_ok=True); open(part, 'w'); raise SystemExit(3)"]
    for _ in range(2):
        with pytest.raises(S.StageError, match=r"stage only stopped \(exit status 3\); run the same command again "
                                               r"to resume"):
            _job(tmp_path, plan=("only",)).run("only", failing, [str(output)])
    assert not (tmp_path / "stages" / "only.json").exists()
    # The rerun of the same command on the same code found the partial output (a tool resumes from it); another
    # command starts from nothing.
    with pytest.raises(S.StageError):
        _job(tmp_path, plan=("only",)).run("only", failing[:1] + [failing[1] + "  # another"], [str(output)])
    assert marker.read_text() == "010"
    with pytest.raises(S.StageError, match=r"stage only finished without writing \["):
        _job(tmp_path, plan=("only",)).run("only", ["-c", "pass"], [str(tmp_path / "never")])


def test_another_command_or_code_removes_the_outputs_first(tmp_path):
    output, marker, lines = tmp_path / "out", tmp_path / "runs.txt", []
    assert _job(tmp_path, plan=("s",)).run("s", _writer(output, marker), [str(output)])
    (output / "stale").write_text("")
    # Same command, other code: removed, run again.
    assert _job(tmp_path, plan=("s",), code="code-2", lines=lines).run("s", _writer(output, marker), [str(output)])
    assert any(f"removing {output}" in line for line in lines) and not (output / "stale").exists()
    # Other command, same code: the same.
    (output / "stale").write_text("")
    assert _job(tmp_path, plan=("s",), code="code-2").run("s", _writer(output, marker, "y"), [str(output)])
    assert not (output / "stale").exists() and marker.read_text() == "xxy"


def test_progress_lines_count_stages_and_estimate_the_time_left(tmp_path):
    marker = tmp_path / "runs.txt"
    commands = {name: _writer(tmp_path / name, marker) for name in ("a", "b", "c")}
    lines = []
    job = _job(tmp_path, plan=("a", "b", "c"), lines=lines)
    for name, command in commands.items():
        job.run(name, command, [str(tmp_path / name)])
    starts = [line for line in lines if line.startswith("\n=== ")]
    assert [line.split(" (")[0] for line in starts] == ["\n=== [1/3] a", "\n=== [2/3] b", "\n=== [3/3] c"]
    assert "left" not in starts[0]  # nothing known yet: no estimate
    assert "about" in starts[1] and "s left" in starts[1]  # the mean of the stages run so far
    assert lines[-1].startswith("=== [3/3] c done in ") and "left" not in lines[-1]
    # Another code: every stage reruns, each estimated from its last record from the start.
    lines.clear()
    job = _job(tmp_path, plan=("a", "b", "c"), code="code-2", lines=lines)
    job.run("a", commands["a"], [str(tmp_path / "a")])
    assert "about" in [line for line in lines if line.startswith("\n=== [1/3] a")][0]
    # Skipped stages say so, with their recorded seconds.
    lines.clear()
    job = _job(tmp_path, plan=("a", "b", "c"), code="code-2", lines=lines)
    job.run("a", commands["a"], [str(tmp_path / "a")])
    assert lines[0].startswith("=== [1/3] a: complete (") and lines[0].endswith(" s when run), skipped")


def test_a_stage_outside_the_plan_is_refused(tmp_path):
    job = _job(tmp_path, plan=("a",))
    with pytest.raises(ValueError, match="not in the plan"):
        job.run("b", ["-c", "pass"], [])
    with pytest.raises(ValueError, match="repeat"):
        _job(tmp_path, plan=("a", "a"))


def test_stages_run_with_this_interpreter_in_the_given_folder(tmp_path):
    (tmp_path / "work").mkdir()
    job = S.Stages(str(tmp_path / "stages"), ["s"], code="c", cwd=str(tmp_path / "work"), log=lambda _: None)
    job.run("s", ["-c", "import os, sys; open('where.txt', 'w').write(os.getcwd() + '\\n' + sys.executable)"],
            [str(tmp_path / "work" / "where.txt")])
    cwd, executable = (tmp_path / "work" / "where.txt").read_text().split("\n")
    assert os.path.samefile(cwd, tmp_path / "work") and executable == sys.executable

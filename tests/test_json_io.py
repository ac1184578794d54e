"""ff3d_tf.json_io: a JSON file is written whole, its folder made, never left half written."""
import json
import os

import pytest

from ff3d_tf import json_io


def test_written_whole_in_a_new_folder(tmp_path):
    path = str(tmp_path / "a" / "b" / "result.json")
    json_io.write_json(path, {"b": 1, "a": [1.5, None]}, sort_keys=True)
    assert json.loads(open(path).read()) == {"a": [1.5, None], "b": 1}
    assert open(path).read().startswith('{\n "a"') and os.listdir(os.path.dirname(path)) == ["result.json"]


def test_a_failed_write_keeps_the_last_complete_file(tmp_path):
    path = str(tmp_path / "result.json")
    json_io.write_json(path, {"step": 1})
    with pytest.raises(TypeError):
        json_io.write_json(path, {"step": 2, "bad": object()})
    assert json.loads(open(path).read()) == {"step": 1}

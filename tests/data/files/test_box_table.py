"""Box tables and sequences of your own sweeps (`ff3d_tf.data.files.box_table`, `sequences`): a valid table read as
CSV and as feather alike, the class map, and every bad table named by file, row and column; timestamps, sequence
listing, and `.npy`/`.npz` headers that lie about their size."""
import os

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest

from ff3d_tf import schema
from ff3d_tf.data.files import box_table, point_files, sequences
from ff3d_tf.data.files.point_file_errors import PointFileError

STEMS = ["000000", "000001", "000002"]
HEADER = "sweep,track_id,class,x,y,z,length,width,height,heading\n"
ROWS = ["000000,car1,vehicle,10,0,0.8,4.5,1.9,1.6,0.0",
        "000001,car1,Vehicle,10.5,0,0.8,4.5,1.9,1.6,0.01",
        "000001,ped7,pedestrian,3,2,0.9,0.6,0.6,1.8,-1.5",
        "000002,ped7,pedestrian,3.1,2,0.9,0.6,0.6,1.8,-1.5",
        "000002,truck,lorry,-20,5,1.5,9,2.5,3.5,3.1"]


def _write(tmp_path, rows, name="boxes.csv", header=HEADER):
    path = tmp_path / name
    path.write_text(header + "".join(r + "\n" for r in rows))
    return str(path)


def _error(path, fn, *args):
    with pytest.raises(PointFileError) as err:
        fn(*args)
    assert str(path) in str(err.value)
    return err.value


def test_a_table_read_as_csv_and_as_feather(tmp_path):
    csv_path = _write(tmp_path, ROWS)
    class_map = {"lorry": schema.CLASS_VEHICLE}
    boxes = box_table.read_box_table(csv_path, STEMS, class_map)
    assert list(boxes) == STEMS
    assert boxes["000001"]["track_id"].tolist() == ["car1", "ped7"]
    assert boxes["000001"]["class_id"].tolist() == [schema.CLASS_VEHICLE, schema.CLASS_PEDESTRIAN]  # any case
    np.testing.assert_array_equal(boxes["000001"]["center"][0], [10.5, 0, 0.8])
    np.testing.assert_array_equal(boxes["000000"]["size"][0], [4.5, 1.9, 1.6])
    assert boxes["000002"]["class_id"].tolist() == [schema.CLASS_PEDESTRIAN, schema.CLASS_VEHICLE]
    cells = [r.split(",") for r in ROWS]
    columns = {c: [row[j] for row in cells] for j, c in enumerate(box_table.BOX_COLUMNS)}
    table = {c: pa.array(v) if c in ("sweep", "track_id", "class") else pa.array([float(x) for x in v])
             for c, v in columns.items()}
    table["speed"] = pa.array([1.0] * len(ROWS))  # other columns are ignored
    feather.write_feather(pa.table(table), str(tmp_path / "boxes.feather"))
    from_feather = box_table.read_box_table(str(tmp_path / "boxes.feather"), STEMS, class_map)
    for stem in STEMS:
        for key in ("center", "size", "heading", "track_id", "class_id"):
            np.testing.assert_array_equal(from_feather[stem][key], boxes[stem][key])
    # a written table reads back bit for bit
    again = box_table.read_box_table(box_table.write_box_table(str(tmp_path / "again.csv"), boxes), STEMS)
    for stem in STEMS:
        np.testing.assert_array_equal(again[stem]["center"], boxes[stem]["center"])


def test_the_class_map(tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text("lorry: vehicle\ncone: background\nDontCare: null\n")
    class_map = box_table.read_class_map(str(path))
    assert class_map == {"lorry": schema.CLASS_VEHICLE, "cone": schema.CLASS_BACKGROUND, "DontCare": None}
    rows = ROWS + ["000000,c1,cone,5,5,0.3,0.3,0.3,0.7,0", "000000,x,DontCare,1,1,1,1,1,1,0"]
    boxes = box_table.read_box_table(_write(tmp_path, rows), STEMS, class_map)
    assert boxes["000000"]["track_id"].tolist() == ["car1", "c1"]  # DontCare dropped, the cone kept as background
    assert boxes["000000"]["class_id"].tolist() == [schema.CLASS_VEHICLE, schema.CLASS_BACKGROUND]
    path.write_text("lorry: truck\n")
    assert "truck" in str(_error(path, box_table.read_class_map, str(path)))
    path.write_text("- a\n- b\n")
    assert "mapping" in str(_error(path, box_table.read_class_map, str(path)))
    path.write_text("a: [unclosed\n")
    assert _error(path, box_table.read_class_map, str(path)).field == "file"


@pytest.mark.parametrize("row, cell, column, says", [
    (ROWS[4], "lorry", "class", "--class_map"),  # an unknown class, unmapped
    (ROWS[0], "4.5", "length", "must be > 0"),  # a negative size
    (ROWS[1], "1.9", "width", "must be > 0"),  # a zero size
    (ROWS[0], "0.8", "z", "not a number"),
    (ROWS[0], "10", "x", "not a finite number"),
    (ROWS[0], "000000", "sweep", "not the name"),
    (ROWS[0], "car1", "track_id", "empty"),
])
def test_a_bad_cell_is_named_by_row_and_column(tmp_path, row, cell, column, says):
    replacement = {"length": "-4.5", "width": "0", "z": "abc", "x": "nan", "sweep": "000099", "track_id": " "}
    i = ROWS.index(row)
    cells = row.split(",")
    cells[box_table.BOX_COLUMNS.index(column)] = replacement.get(column, cell)
    rows = ROWS[:i] + [",".join(cells)] + ROWS[i + 1:]
    path = _write(tmp_path, rows)
    err = _error(path, box_table.read_box_table, path, STEMS)
    assert err.field == f"row {i + 1} (line {i + 2}), column {column}" and says in err.reason, str(err)


def test_bad_tables_name_file_row_and_column(tmp_path):
    path = _write(tmp_path, ROWS, header=HEADER.replace(",heading", ""))
    assert _error(path, box_table.read_box_table, path, STEMS).field == "column heading"
    # a track that jumps a sweep: seen in 000000 and 000002, not in 000001
    rows = ROWS[:1] + ROWS[2:4] + ["000002,car1,vehicle,11,0,0.8,4.5,1.9,1.6,0.02"]
    path = _write(tmp_path, rows)
    err = _error(path, box_table.read_box_table, path, STEMS)
    assert err.field == "row 4 (line 5), column track_id" and "consecutive" in err.reason and "'car1'" in err.reason
    path = _write(tmp_path, ROWS[:4] + [ROWS[3]])  # the same track twice in a sweep
    err = _error(path, box_table.read_box_table, path, STEMS)
    assert err.field == "row 5 (line 6), column track_id" and "row 4" in err.reason
    path = _write(tmp_path, ROWS + ["000001,car9,vehicle,1,2"])
    assert _error(path, box_table.read_box_table, path, STEMS).field == "row 6 (line 7)"
    path = tmp_path / "latin.csv"
    path.write_bytes(HEADER.encode() + "000000,caf\xe9,vehicle,1,1,1,1,1,1,0\n".encode("latin-1"))
    assert _error(path, box_table.read_box_table, str(path), STEMS).field == "file"
    path = tmp_path / "boxes.feather"
    feather.write_feather(pa.table({c: pa.array([1.0]) for c in box_table.BOX_COLUMNS}), str(path))
    assert _error(path, box_table.read_box_table, str(path), STEMS).field == "column sweep"  # a number, not text
    path.write_bytes(b"ARROW1 not really")
    assert _error(path, box_table.read_box_table, str(path), STEMS).field == "file"
    cols = {c: pa.array(["000000"]) if c in ("sweep", "track_id", "class") else pa.array([1.0])
            for c in box_table.BOX_COLUMNS}
    cols["class"] = pa.array(["vehicle"])
    cols["height"] = pa.array([None], pa.float64())  # a null
    feather.write_feather(pa.table(cols), str(path))
    assert _error(path, box_table.read_box_table, str(path), STEMS).field == "row 1, column height"


def test_timestamps_and_sequences(tmp_path):
    seq = tmp_path / "run1"
    xyz = np.random.default_rng(0).uniform(-5, 5, (20, 3)).astype(np.float32)
    sequences.write_sequence(str(seq), [(s, xyz, np.zeros(20)) for s in STEMS], [np.eye(4)] * 3,
                             [1_600_000_000_000_000_000, 1_600_000_000_100_000_001, 1_600_000_000_200_000_000])
    s = sequences.read_sequence(str(seq))
    assert s.timestamps_ns == (1_600_000_000_000_000_000, 1_600_000_000_100_000_001, 1_600_000_000_200_000_000)
    assert s.timestamps_from == "timestamps.txt" and s.box_table is None and len(s.poses) == 3 and s.name == "run1"
    assert sequences.list_sequences(str(seq)) == [str(seq)]
    assert sequences.list_sequences(str(tmp_path)) == [str(seq)]
    assert sequences.list_sequences(str(tmp_path / "run*")) == [str(seq)]
    with pytest.raises(FileNotFoundError):
        sequences.list_sequences(str(tmp_path / "none*"))
    stamps = seq / "timestamps.txt"
    stamps.write_text("0.0\n0.2 # a comment\n\n0.1\n")
    err = _error(stamps, sequences.read_sequence, str(seq))
    assert err.field == "line 4" and "not after" in err.reason
    stamps.write_text("0.0\n0.1\n")
    assert "2 times for 3 sweeps" in str(_error(stamps, sequences.read_sequence, str(seq)))
    stamps.write_text("0.0\n0.1\nsoon\n")
    assert _error(stamps, sequences.read_sequence, str(seq)).field == "line 3"
    stamps.write_text("0\ninf\n1\n")
    assert _error(stamps, sequences.read_sequence, str(seq)).field == "line 2"
    os.remove(stamps)
    s = sequences.read_sequence(str(seq), sweep_period_s=0.05)
    assert s.timestamps_ns == (0, 50_000_000, 100_000_000) and "0.05" in s.timestamps_from


def test_npy_and_npz_headers_that_lie_are_named_before_any_allocation(tmp_path):
    """A header claiming 4e9 x 4 float32 (64 GB) is checked against the file's size: an error naming the file, not a
    MemoryError from an allocation of what the header says."""
    from numpy.lib import format as npy_format
    path = tmp_path / "huge.npy"
    with open(path, "wb") as f:
        npy_format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": (4_000_000_000, 4)})
        f.write(np.zeros((10, 4), "<f4").tobytes())
    err = _error(path, point_files.read_point_file, str(path))
    assert "(4000000000, 4)" in err.reason and "truncated" in err.reason
    import zipfile
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open("points.npy", "w") as member:
            npy_format.write_array_header_1_0(member, {"descr": "<f4", "fortran_order": False,
                                                       "shape": (1_000_000_000, 3)})
            member.write(np.zeros((5, 3), "<f4").tobytes())
    assert "points" == _error(path, point_files.read_point_file, str(path)).field
    path = tmp_path / "ok.npz"
    np.savez_compressed(path, points=np.ones((7, 4), np.float32))
    assert point_files.read_point_file(str(path)).xyz.shape == (7, 3)
    path = tmp_path / "pose.npy"
    np.save(path, np.array(["a"] * 16).reshape(4, 4))
    assert _error(path, point_files.read_pose, str(path)).field == "pose"

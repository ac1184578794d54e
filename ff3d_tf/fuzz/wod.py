"""Fuzzing of the WOD reader: damaged records (`wod_mutants`) decoded one by one, and whole files (a damaged record
among good ones, or the file cut at a random byte) read by `read_frames` and the tf.data pair pipeline.

A named error is a `FrameDecodeError` naming the file, the damaged record and a field (`classify_decode`).
"""
from __future__ import annotations

import os

import numpy as np
import tensorflow as tf

from ff3d_tf.data import pairs
from ff3d_tf.data.wod import waymo
from ff3d_tf.data.wod_errors import FrameDecodeError
from ff3d_tf.fuzz import wod_mutants
from ff3d_tf.fuzz.report import SECONDS_PER_INPUT, Report, check_frame, judge

# Decoder options the mutants cycle through: (returns, with_pixels).
ALL_OPTION_SETS = (((1,), False), ((1, 2), True), ((1,), True), ((1, 2), False))
FILE_FACTOR = 6  # a whole file may take this many times the per-input bounds (time and watchdog)
TFRECORD_FRAMING_BYTES = 16  # per record: length, its CRC and the data's CRC


def classify_decode(call, path: str, record_index: int) -> tuple[str, str]:
    """(outcome, detail) of decoding one record: `call()` returns the frame dict or raises."""
    try:
        frame = call()
    except FrameDecodeError as err:
        msg = str(err)
        named = (path in msg and f"record {record_index}" in msg and err.field not in ("", "unknown")
                 and f"field {err.field}" in msg)
        return ("named_error" if named else "unnamed_error"), msg
    except tf.errors.OpError as err:
        return "raw_error", f"{type(err).__name__}: {err.message[:300]}"
    except Exception as err:  # noqa: BLE001 - any other exception is a defect to report, not to hide
        return "crash", f"{type(err).__name__}: {err}"
    problem = check_frame(frame)
    return ("nonfinite", problem) if problem else ("decoded", f"{len(frame['points_xyz'])} points")


def fuzz_records(records: list[bytes], num_mutants: int, seed: int = 0, kinds=wod_mutants.KINDS,
                 report: Report | None = None, option_sets=ALL_OPTION_SETS, hang_s: float | None = None) -> Report:
    """Decodes `num_mutants` damaged copies of `records` (kinds round-robin) with `waymo.decode_frame`; `hang_s`:
    the watchdog's bound on one input (None: none)."""
    report = report if report is not None else Report()
    rng = np.random.default_rng(seed)
    for returns, with_pixels in option_sets:  # trace the decoders first: tracing is not decoding time
        waymo.decode_frame(records[0], with_pixels=with_pixels, returns=returns)
    for i in range(num_mutants):
        kind = kinds[i % len(kinds)]
        returns, with_pixels = option_sets[(i // len(kinds)) % len(option_sets)]
        mutant, what = wod_mutants.mutate(records[int(rng.integers(len(records)))], kind, rng)
        path = f"mutant-{kind}.tfrecord"

        def decode():
            return waymo.decode_frame(mutant, source=path, record_index=i, with_pixels=with_pixels, returns=returns)

        judge(report, kind, f"{what} (returns {returns})", lambda: classify_decode(decode, path, i), hang_s)
    return report


def write_records(path: str, records) -> str:
    with tf.io.TFRecordWriter(path) as writer:
        for record in records:
            writer.write(record)
    return path


def _damaged_file(path: str, records: list[bytes], i: int, rng) -> tuple[str, int, str]:
    """Writes file `i` of a run (odd: cut at a random byte, even: one damaged record): (kind, index of the first
    damaged record, what was done)."""
    if i % 2:
        write_records(path, records)
        size = os.path.getsize(path)
        cut = int(rng.integers(1, size))
        with open(path, "r+b") as f:
            f.truncate(cut)
        offsets = np.cumsum([0] + [len(r) + TFRECORD_FRAMING_BYTES for r in records])  # record k: [o[k], o[k+1])
        bad_index = int(np.searchsorted(offsets, cut, side="right") - 1)
        return "truncate_file", bad_index, f"file cut at byte {cut} of {size} (inside record {bad_index})"
    bad_index = int(rng.integers(len(records)))
    mutant, what = wod_mutants.mutate(records[bad_index], wod_mutants.KINDS[int(rng.integers(len(wod_mutants.KINDS)))],
                                      rng)
    write_records(path, records[:bad_index] + [mutant] + records[bad_index + 1:])
    return "mixed_file", bad_index, what


def fuzz_files(records: list[bytes], out_dir: str, num_files: int, seed: int = 0, cfg=None,
               report: Report | None = None, num_pair_files: int = 4, hang_s: float | None = None) -> Report:
    """Whole files, read by `read_frames` (Python-driven) and, for the first `num_pair_files` when `cfg` is given, by
    the tf.data pair pipeline (`pairs.pair_dataset`: seconds per file, as each builds its own pipeline); `hang_s`:
    the watchdog's bound on one input, `FILE_FACTOR` times it per file (None: none).

    A named error must name this file and the damaged record (a cut file: the first record it breaks)."""
    report = report if report is not None else Report()
    rng = np.random.default_rng(seed)
    os.makedirs(out_dir, exist_ok=True)
    for i in range(num_files):
        path = os.path.join(out_dir, f"file-{i}.tfrecord")
        kind, bad_index, what = _damaged_file(path, records, i, rng)
        readers = {"read_frames": lambda: _read_all(waymo.read_frames(path))}
        if cfg is not None and i < num_pair_files:
            readers["pair_dataset"] = lambda: _pairs_all(path, cfg)
        for reader, call in readers.items():
            def classify():
                outcome, detail = classify_decode(call, path, bad_index)
                if outcome == "named_error" and f"record {bad_index}:" not in detail:
                    outcome = "unnamed_error"  # names a record, but not the damaged one
                return outcome, detail

            judge(report, f"{kind}/{reader}", what, classify, None if hang_s is None else FILE_FACTOR * hang_s,
                  FILE_FACTOR * SECONDS_PER_INPUT)
    return report


def _read_all(frames) -> dict:
    """Reads every frame; returns a frame dict concatenating all of them (for `check_frame`)."""
    decoded = [f for _, _, f in frames]
    if not decoded:
        raise AssertionError("no frame decoded")
    merged = {k: np.concatenate([f[k] for f in decoded]) for k in decoded[0] if k not in ("pose", "timestamp_micros")}
    merged["pose"] = np.stack([f["pose"] for f in decoded])
    return merged


def _pairs_all(path: str, cfg) -> dict:
    """Reads every pair of the file through the pair pipeline; returns the first pair's t0 as a frame dict."""
    with pairs.input_errors_named([path], pairs.decode_options(cfg)):
        examples = [{k: v.numpy() for k, v in ex.items()} for ex in pairs.pair_dataset([path], cfg)]
    if not examples:
        raise AssertionError("no pair decoded")
    ex = examples[0]
    return {"points_xyz": ex["points_xyz_t0"], "intensity": ex["point_features_t0"][:, 0],
            "elongation": ex["point_features_t0"][:, 1], "flow_mps": ex["flow_mps_t0"], "class_id": ex["class_id_t0"],
            "laser_name": np.zeros(len(ex["class_id_t0"]), np.int32), "pose": ex["pose_t0"]}

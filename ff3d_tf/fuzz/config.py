"""Fuzzing of the YAML config loader (`ff3d_tf.config.load_config`): the default config damaged one key per mutant
(wrong type, unknown key, out of range, non-finite, wrong length, a section not a mapping, broken YAML).

A named error is a `ConfigError` naming the key and what is allowed; an accepted config must be finite and round-trip
through its saved YAML.
"""
from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import yaml

from ff3d_tf.config import ConfigError, ExperimentConfig, load_config
from ff3d_tf.fuzz.report import Report, judge, pick

KINDS = ("wrong_type", "unknown_key", "out_of_range", "non_finite", "wrong_length", "not_a_mapping", "broken_yaml")
_WRONG_VALUES = ("text", [1, 2], {"a": 1}, True, None, 1.5, -3, "1e-3x", [[1]])


def mutate(rng: np.random.Generator, kind: str) -> tuple[str, str, str]:
    """(YAML text, the dotted key it damages, what was done) from the default config."""
    tree = json_tree(ExperimentConfig())
    section = pick(rng, sorted(tree))
    key = pick(rng, sorted(tree[section]))
    default = tree[section][key]
    dotted = f"{section}.{key}"
    if kind == "wrong_type":
        value = pick(rng, [v for v in _WRONG_VALUES if type(v) is not type(default)])
        tree[section][key] = value
        what = f"{dotted} = {value!r}"
    elif kind == "unknown_key":
        typo = key[:-1] if rng.random() < 0.5 else key + "s"
        if rng.random() < 0.2:
            tree[section + "x"] = {key: default}
            dotted, what = section + "x", f"section {section}x"
        else:
            tree[section][typo] = default
            dotted, what = f"{section}.{typo}", f"{section}.{typo}"
    elif kind == "out_of_range":
        value = _out_of_range(default, rng)
        tree[section][key] = value
        what = f"{dotted} = {value!r}"
    elif kind == "non_finite":
        value = pick(rng, [float("nan"), float("inf"), float("-inf")])
        tree[section][key] = [value, value] if isinstance(default, list) else value
        what = f"{dotted} = {tree[section][key]!r}"
    elif kind == "wrong_length":
        if isinstance(default, list):
            value = default + default[:1] if rng.random() < 0.5 else default[:-1]
        else:
            value = [default]
        tree[section][key] = value
        what = f"{dotted} = {value!r}"
    elif kind == "not_a_mapping":
        tree[section] = pick(rng, [[1, 2], "text", 3])
        dotted, what = section, f"section {section} = {tree[section]!r}"
    elif kind == "broken_yaml":
        text = yaml.safe_dump(tree)
        cut = int(rng.integers(1, len(text)))
        broken = text[:cut] + pick(rng, [": [", "\t", "{", "- -", "!!python/object:os.system x", "\x00"]) + text[cut:]
        return broken, "", f"YAML broken at character {cut}"
    else:
        raise ValueError(f"unknown config mutation kind {kind!r}; one of {KINDS}")
    return yaml.safe_dump(tree, sort_keys=False, allow_unicode=True), dotted, what


def json_tree(cfg) -> dict:
    """The config as plain YAML-able data (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def _out_of_range(default, rng):
    if isinstance(default, bool):
        return 2
    if isinstance(default, int):
        return pick(rng, [-1, -(2 ** 40), 0, 2 ** 62])
    if isinstance(default, float):
        return pick(rng, [-1.0, 0.0, 1e30, -1e-9, 2.0])
    if isinstance(default, str):
        return "no_such_option"
    if isinstance(default, list):
        if default and isinstance(default[0], list):
            return [[-1, 0]] * len(default)
        return [pick(rng, [-5, 0, 99])] * len(default) if default else [7]
    return -1


_ALLOWED_WORDS = ("expected", "must", "one of", "known", "allowed", "need", "each", "multiple of", "in [", "in (",
                  ">=", "> 0", "mapping", "true/false", "a number", "an integer", "list")


def classify(text: str, dotted: str, tmp_path: str) -> tuple[str, str]:
    """(outcome, detail) of loading the YAML `text` (written to `tmp_path`) that damages the key `dotted`."""
    with open(tmp_path, "w", encoding="utf-8") as f:
        f.write(text)
    try:
        cfg = load_config(tmp_path)
    except ConfigError as err:
        msg = str(err)
        key_named = (not dotted or dotted in msg or dotted.split(".")[-1] in msg)
        allowed = any(w in msg for w in _ALLOWED_WORDS) or "YAML" in msg
        return ("named_error" if key_named and allowed else "unnamed_error"), msg
    except Exception as err:  # noqa: BLE001 - any other exception is a defect to report, not to hide
        return "crash", f"{type(err).__name__}: {err}"
    values = [v for section in json_tree(cfg).values() for v in section.values()]
    flat = np.asarray([x for v in values for x in np.ravel(np.asarray(v, dtype=object))
                       if isinstance(x, float)], np.float64)
    if not np.all(np.isfinite(flat)):
        return "nonfinite", "accepted a non-finite value"
    cfg.save(tmp_path + ".resolved.yaml")
    if load_config(tmp_path + ".resolved.yaml") != cfg:
        return "crash", "accepted config does not round-trip through its saved YAML"
    return "decoded", "accepted"


def fuzz_configs(work_dir: str, num_mutants: int, seed: int = 0, report: Report | None = None,
                 hang_s: float | None = None) -> Report:
    """Loads `num_mutants` damaged configs (kinds round-robin); `hang_s`: the watchdog's bound on one input (None:
    none). Configs have no `slow` bound."""
    report = report if report is not None else Report()
    rng = np.random.default_rng(seed)
    os.makedirs(work_dir, exist_ok=True)
    path = os.path.join(work_dir, "mutant.yaml")
    ExperimentConfig().save(os.path.join(work_dir, "default.yaml"))  # imports TensorFlow once, outside the timing
    for i in range(num_mutants):
        kind = KINDS[i % len(KINDS)]
        text, dotted, what = mutate(rng, kind)
        judge(report, kind, what, lambda: classify(text, dotted, path), hang_s, bound_s=None)
    return report

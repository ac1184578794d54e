"""Damaged YAML configs end as a `ConfigError` naming the key and what is allowed, or a config that round-trips."""
import numpy as np

from ff3d_tf.fuzz import config


def test_config_mutants(tmp_path):
    report = config.fuzz_configs(str(tmp_path), 40 * len(config.KINDS), seed=4)
    assert not report.defects, report.format("defects")
    assert set(report.table()) == set(config.KINDS)
    assert all(counts["named_error"] > 0 for counts in report.table().values())


def test_the_default_config_is_accepted(tmp_path):
    import yaml
    text = yaml.safe_dump(config.json_tree(config.ExperimentConfig()))
    assert config.classify(text, "", str(tmp_path / "default.yaml")) == ("decoded", "accepted")


def test_mutants_are_reproducible_by_seed():
    first = [config.mutate(np.random.default_rng(3), kind) for kind in config.KINDS]
    assert first == [config.mutate(np.random.default_rng(3), kind) for kind in config.KINDS]

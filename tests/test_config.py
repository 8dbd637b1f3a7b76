from pathlib import Path

import pytest

from service.config import Config, ConfigError, default_yaml, load_config

ROOT = Path(__file__).resolve().parents[1]


def test_default_yaml_equals_dataclass_defaults():
    text = (ROOT / "configs" / "default.yaml").read_text()
    assert text == default_yaml(), "regenerate: mnemoslam config > configs/default.yaml"
    assert load_config(ROOT / "configs" / "default.yaml") == Config()


def test_partial_file_and_overrides(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("odometry:\n  min_inliers: 30\nkeyframe:\n  linear_update: 1\n")
    c = load_config(p, {"odometry": {"match_ratio": 0.7}})
    assert c.odometry.min_inliers == 30 and c.odometry.match_ratio == 0.7
    assert c.keyframe.linear_update == 1.0 and isinstance(c.keyframe.linear_update, float)
    assert c.features == Config().features


@pytest.mark.parametrize("text,match", [
    ("odometry:\n  min_inlier: 3\n", "unknown config key 'odometry.min_inlier'"),
    ("odometry:\n  min_inliers: lots\n", "expected int"),
    ("odometry: [1, 2]\n", "expected a mapping"),
    ("odometry: {\n", "invalid YAML"),
])
def test_bad_config_is_a_clear_error(tmp_path, text, match):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(p)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "none.yaml")

from pathlib import Path

import pytest

from mnemoslam.service.config import Config, ConfigError, default_yaml, load_config

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


def test_set_items_are_typed_overrides():
    from mnemoslam.service.config import parse_sets

    o = parse_sets(["loop.enabled=false", "service.queue_size=30", "storage.path=/tmp/m.db", "seed=3",
                    "zenoh.connect=[tcp/10.0.0.1:7447]", "loop.threshold=0.2", "service.queue_size=31"])
    assert o == {"loop": {"enabled": False, "threshold": 0.2}, "service": {"queue_size": 31},
                 "storage": {"path": "/tmp/m.db"}, "seed": 3, "zenoh": {"connect": ["tcp/10.0.0.1:7447"]}}
    c = load_config(None, o)
    assert c.loop.enabled is False and c.service.queue_size == 31 and c.zenoh.connect == ["tcp/10.0.0.1:7447"]
    assert parse_sets(None) == {} and parse_sets([]) == {}


@pytest.mark.parametrize("items,match", [
    (["loop.enabled"], "expected KEY=VALUE"),
    (["=1"], "expected KEY=VALUE"),
    (["loop..enabled=1"], "expected KEY=VALUE"),
    (["loop.enabled=[1"], "not valid YAML"),
    (["loop={enabled: false}"], "scalar or a list"),
    (["seed=1", "seed.x=2"], "seed is set to a value"),
    (["loop.enabled=false", "loop=1"], "other --set items set keys inside it"),
])
def test_bad_set_items(items, match):
    from mnemoslam.service.config import parse_sets

    with pytest.raises(ConfigError, match=match):
        parse_sets(items)


@pytest.mark.parametrize("items,match", [
    (["loop.enable=false"], "unknown config key 'loop.enable'"),
    (["service.queue_size=many"], "'service.queue_size': expected int"),
    (["loop=false"], "loop: expected a mapping"),  # a section set to a scalar is no longer ignored
    (["seed.x=1"], "'seed': expected int"),
])
def test_set_items_checked_by_the_typed_loader(items, match):
    from mnemoslam.service.config import parse_sets

    with pytest.raises(ConfigError, match=match):
        load_config(None, parse_sets(items))

"""config: a YAML text is composed once per process; every load gets its own copy."""

import pytest

from rig_runtime import config
from rig_runtime.errors import ConfigError


def test_same_text_parsed_once_each_caller_its_own_copy(monkeypatch):
    monkeypatch.setenv("RIG_CACHE_DIR", "")     # this process's own copies (the disk's: tests/test_memo_disk.py)
    calls = []
    compose = config._compose_bounded
    monkeypatch.setattr(config, "_compose_bounded", lambda text: calls.append(text) or compose(text))
    text = "a: {b: [1, 2.0e3, x]}\ninclude: [other.yaml]\n"
    first = config._load_yaml_bounded(text)
    first.pop("include")
    first["a"]["b"].append("changed")
    second = config._load_yaml_bounded(text)
    assert second == {"a": {"b": [1, 2000.0, "x"]}, "include": ["other.yaml"]}
    assert calls == [text]
    assert config._load_yaml_bounded(text + "c: 1\n")["c"] == 1
    assert len(calls) == 2


def test_a_refused_text_is_refused_every_time(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("a: [1, 2\n")
    for _ in range(2):
        with pytest.raises(ConfigError, match="valid YAML"):
            config.read_config_file(p)


def test_loading_a_config_twice_gives_equal_configs():
    assert config.load(config.CONFIG_DIR / "sim.yaml") == config.load(config.CONFIG_DIR / "sim.yaml")

from pathlib import Path

import pytest

from slam2d.config import SlamConfig, config_from_dict, dump_config, load_config
from slam2d.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_default_yaml_is_dump_config_output():
    assert (ROOT / "configs" / "default.yaml").read_text() == dump_config()


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_config_loads(path):
    assert isinstance(load_config(path), SlamConfig)


def test_dump_round_trips_changed_values(tmp_path):
    cfg = config_from_dict({"grid": {"resolution": 0.1}, "submaps": {"num_range_data": 33}})
    f = tmp_path / "c.yaml"
    f.write_text(dump_config(cfg))
    again = load_config(f)
    assert again == cfg
    assert again.grid.resolution == 0.1 and again.submaps.num_range_data == 33


def test_every_option_has_a_description():
    for name, field in SlamConfig.model_fields.items():
        assert field.description
        for key, sub in type(getattr(SlamConfig(), name)).model_fields.items():
            assert sub.description, f"{name}.{key}"


@pytest.mark.parametrize("data, needle", [
    ({"grid": {"hit_probability": 1.5}}, "grid.hit_probability"),
    ({"grid": {"miss_probability": 0.6}}, "grid.miss_probability"),
    ({"grdi": {}}, "unknown key 'grdi'"),
    ({"grid": {"resolutoin": 0.05}}, "unknown key 'grid.resolutoin'"),
    ({"real_time_matcher": {"linear_search_window": 0}}, "real_time_matcher.linear_search_window"),
    ({"map": {"free_thresh": 0.9}}, "free_thresh"),
    # YAML's true is no number (pydantic read it as 1.0); cells under 1 cm asked for exabytes
    ({"range_filter": {"max_range": True}}, "range_filter.max_range': Value error, needs a number, not true"),
    ({"submaps": {"num_range_data": False}}, "submaps.num_range_data': Value error, needs a number, not false"),
    ({"grid": {"resolution": 1e-9}}, "grid.resolution': Input should be greater than or equal to 0.01"),
])
def test_bad_values_name_the_key(data, needle):
    with pytest.raises(ConfigError) as e:
        config_from_dict(data, "user.yaml")
    assert needle in str(e.value)
    assert "user.yaml" in str(e.value)


def test_bad_yaml_names_file_and_line(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("grid:\n  resolution: [0.05\n")
    with pytest.raises(ConfigError) as e:
        load_config(f)
    assert str(f) in str(e.value) and "YAML" in str(e.value)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="no such config file"):
        load_config(tmp_path / "nope.yaml")


def test_a_bad_value_set_in_code_is_a_config_error():
    """cfg.grid.resolution = -1 raised pydantic's ValidationError; the YAML path names the key as a ConfigError."""
    cfg = SlamConfig()
    with pytest.raises(ConfigError, match=r"^GridConfig: key 'resolution': Input should be greater than or equal to 0.01"):
        cfg.grid.resolution = -1
    cfg.grid.resolution = 0.1
    assert cfg.grid.resolution == 0.1

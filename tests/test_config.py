"""Configuration: dataclass defaults, then YAML, then key=value overrides; unknown keys and bad
values fail naming the key; every named preset and registry name is checked when loaded."""
import pytest

from mona_vo.config import load_config, parse_set_options, to_dict
from mona_vo.errors import ConfigError
from mona_vo.pipeline import PipelineConfig
from mona_vo.presets import PRESETS


def test_dotted_overrides_reach_nested_sections_with_types():
    cfg = load_config(PipelineConfig, None, parse_set_options(
        ["vo.grid_size=20", "vo.ba.robust_kernel=cauchy", "masks.prompt=points", "vo.refine_focal=true"]))
    assert cfg.vo.grid_size == 20 and isinstance(cfg.vo.grid_size, int)
    assert cfg.vo.ba.robust_kernel == "cauchy" and cfg.masks.prompt == "points" and cfg.vo.refine_focal is True
    assert PipelineConfig().vo.grid_size != 20   # defaults untouched (frozen dataclasses)


@pytest.mark.parametrize("item, fragment", [
    ("vo.grid_sise=20", "vo.grid_sise"),               # typo: unknown key
    ("vo.grid_size=twenty", "vo.grid_size"),           # not a number
    ("vo.grid_size=2.5", "vo.grid_size"),              # not an integer
    ("vo.refine_focal=maybe", "vo.refine_focal"),      # not a boolean
    ("vo.tracker=sift", "tracker"),                    # not a registered back end
    ("masks.prompt=boxes-and-points", "prompt"),       # not a prompt mode
    ("vo.ba.robust_kernel=tukey", "robust_kernel"),
    ("vo=3", "section"),                               # a section is not a value
])
def test_bad_overrides_fail_naming_the_key(item, fragment):
    with pytest.raises(ConfigError, match=fragment):
        load_config(PipelineConfig, None, parse_set_options([item]))


def test_set_option_needs_key_equals_value():
    with pytest.raises(ConfigError, match="key=value"):
        parse_set_options(["vo.grid_size"])


def test_yaml_then_overrides(tmp_path):
    path = tmp_path / "cfg.yaml"
    path.write_text("vo:\n  grid_size: 12\n  ba:\n    max_iterations: 3\nmasks:\n  tau0: 5\n")
    cfg = load_config(PipelineConfig, path, {"vo.grid_size": "14"})
    assert (cfg.vo.grid_size, cfg.vo.ba.max_iterations, cfg.masks.tau0) == (14, 3, 5.0)
    bad = tmp_path / "bad.yaml"
    bad.write_text("vo: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(PipelineConfig, bad)
    with pytest.raises(ConfigError, match="not found"):
        load_config(PipelineConfig, tmp_path / "missing.yaml")


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_loads_and_round_trips_through_its_dict(name):
    cfg = load_config(PipelineConfig, None, PRESETS[name])
    again = load_config(PipelineConfig, None, {k: v for k, v in to_dict(cfg).items()})
    assert again == cfg

"""Configuration: dataclass defaults, then YAML, then key=value overrides. Every key declares its
rule where it is defined (mona_vo.config.setting); unknown keys, bad types and values out of range
fail with one line naming the key as typed; `mona-vo config`'s YAML loads back to the same
config; pyproject's dependency ranges hold the versions CI installs."""
import dataclasses
import re
import tomllib
from pathlib import Path

import pytest

from mona_vo.config import RULE, field_docs, leaves, load_config, parse_set_options, to_dict, to_yaml
from mona_vo.errors import ConfigError
from mona_vo.pipeline import PipelineConfig
from mona_vo.presets import PRESETS

ROOT = Path(__file__).resolve().parents[1]
LEAVES = [(key, f, value, kind) for key, f, value, kind in leaves(PipelineConfig())]


def test_dotted_overrides_reach_nested_sections_with_types():
    cfg = load_config(PipelineConfig, None, parse_set_options(
        ["vo.grid_size=20", "vo.ba.robust_kernel=cauchy", "masks.prompt=points", "vo.refine_focal=true"]))
    assert cfg.vo.grid_size == 20 and isinstance(cfg.vo.grid_size, int)
    assert cfg.vo.ba.robust_kernel == "cauchy" and cfg.masks.prompt == "points" and cfg.vo.refine_focal is True
    assert PipelineConfig().vo.grid_size != 20   # defaults untouched (frozen dataclasses)


@pytest.mark.parametrize("item, message", [
    ("vo.grid_sise=20", "unknown config key 'vo.grid_sise'; did you mean 'vo.grid_size'?"),
    ("vo.grid_size=twenty", "config key 'vo.grid_size': expected an integer, got 'twenty'"),
    ("vo.grid_size=2.5", "config key 'vo.grid_size': expected an integer"),
    ("vo.refine_focal=maybe", "config key 'vo.refine_focal': expected true or false"),
    ("tracker=sift", "config key 'tracker': 'sift' is not allowed; expected one of"),
    ("masks.prompt=boxes-and-points", "config key 'masks.prompt'"),
    ("vo.ba.robust_kernel=tukey", "config key 'vo.ba.robust_kernel': 'tukey' is not allowed; "
                                  "expected one of huber, cauchy, none"),
    ("vo.keyframe_max_gap=0", "config key 'vo.keyframe_max_gap': 0 is not allowed; expected an integer >= 1"),
    ("vo.ba.max_iterations=-1", "config key 'vo.ba.max_iterations': -1 is not allowed"),
    ("masks.dynamic_points.window=1", "config key 'masks.dynamic_points.window'"),
    ("masks.dis.scale=1.5", "config key 'masks.dis.scale': 1.5 is not allowed; expected a number in (0, 1]"),
    ("vo.grid_size=nan", "config key 'vo.grid_size': expected a finite number"),
    ("vo=3", "section"),                               # a section is not a value
    ("vo.grid_size.x=3", "has no sub-keys"),
    ("vo.tracker=lk", "unknown config key 'vo.tracker'"),   # one tracker key: the top-level one
])
def test_bad_overrides_fail_naming_the_key(item, message):
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        load_config(PipelineConfig, None, parse_set_options([item]))
    assert "\n" not in str(err.value)


def test_every_leaf_key_has_a_rule_and_a_doc():
    assert len(LEAVES) > 50
    missing = [key for key, f, _, _ in LEAVES if RULE not in f.metadata]
    assert not missing, f"declare these with mona_vo.config.setting: {missing}"
    undocumented = []
    for key, f, _, _ in LEAVES:
        section = PipelineConfig()
        for part in key.split(".")[:-1]:
            section = getattr(section, part)
        if not field_docs(type(section)).get(f.name):
            undocumented.append(key)
    assert not undocumented, f"give these a comment: {undocumented}"


def test_numbers_have_a_range_and_text_a_set_of_choices_or_a_stated_meaning():
    for key, f, _, kind in LEAVES:
        rule = f.metadata[RULE]
        if kind in (int, float):
            assert any(b is not None for b in (rule.ge, rule.gt, rule.le, rule.lt)), key
        elif kind is str:
            assert rule.choices is not None or rule.pattern or rule.text, key


@pytest.mark.parametrize("key", [key for key, *_ in LEAVES])
def test_every_key_refuses_a_value_out_of_its_range_naming_the_key(key):
    f, value, kind = next((f, v, k) for k_, f, v, k in LEAVES if k_ == key)
    assert f.metadata[RULE].allows(value), f"the default of {key} breaks its own rule"
    bad = f.metadata[RULE].out_of_range_example(kind)
    if kind is bool:
        bad = "maybe"
    elif kind in (int, float) and bad is None:
        pytest.fail(f"{key}: a number without bounds")
    elif bad is None:
        bad = {"not": "text"}      # free text: only the type can be wrong
    with pytest.raises(ConfigError, match=re.escape(f"config key '{key}'")):
        load_config(PipelineConfig, None, {key: bad})
    if kind in (int, float):
        with pytest.raises(ConfigError, match=re.escape(f"config key '{key}': expected")):
            load_config(PipelineConfig, None, {key: "abc"})


def test_cross_field_rule_names_both_keys():
    with pytest.raises(ConfigError, match="'vo.window_keyframes' .* 'vo.fixed_keyframes'"):
        load_config(PipelineConfig, None, {"vo.window_keyframes": 3, "vo.fixed_keyframes": 3})
    # Checked once at the end: a YAML value may rely on a --set value given after it.
    cfg = load_config(PipelineConfig, None, {"vo.fixed_keyframes": 9, "vo.window_keyframes": 12})
    assert (cfg.vo.fixed_keyframes, cfg.vo.window_keyframes) == (9, 12)


def test_a_stage_built_in_code_is_checked_too():
    from mona_vo.vo import VOConfig, VisualOdometry

    with pytest.raises(ConfigError, match="'vo.keyframe_max_gap'"):
        VisualOdometry(dataclasses.replace(VOConfig(), keyframe_max_gap=0), 64, 48)


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
    typo = tmp_path / "typo.yaml"
    typo.write_text("vo:\n  ba:\n    max_iteration: 3\n")
    with pytest.raises(ConfigError, match=re.escape(f"{typo}: unknown config key 'vo.ba.max_iteration'")):
        load_config(PipelineConfig, typo)
    boolean = tmp_path / "bool.yaml"
    boolean.write_text("vo:\n  grid_size: true\n")
    with pytest.raises(ConfigError, match="'vo.grid_size': expected an integer"):
        load_config(PipelineConfig, boolean)


def test_printed_yaml_documents_every_key_and_loads_back_to_the_same_config(tmp_path):
    for name in sorted(PRESETS):
        cfg = load_config(PipelineConfig, None, PRESETS[name])
        text = to_yaml(cfg)
        path = tmp_path / f"{name}.yaml"
        path.write_text(text)
        again = load_config(PipelineConfig, path)
        assert again == cfg and to_dict(again) == to_dict(cfg)
    lines = to_yaml(PipelineConfig()).splitlines()
    keys = [i for i, line in enumerate(lines) if not line.lstrip().startswith("#")]
    assert all(lines[i - 1].lstrip().startswith("# ") for i in keys)    # a comment above each key
    assert "  # k: new points on a k x k grid, one per cell [an integer >= 2]" in lines  # vo.grid_size
    values = [line for line in lines if ":" in line and not line.lstrip().startswith("#")
              and not line.rstrip().endswith(":")]
    assert len(values) == len(LEAVES)


def test_one_key_per_fact():
    names = [key.rsplit(".", 1)[-1] for key, *_ in LEAVES]
    for fact in ("tracker", "assumed_hfov_deg", "device", "weights", "tracker_checkpoint"):
        assert names.count(fact) == 1, fact


def test_the_assumed_field_of_view_reaches_masks_and_vo(monkeypatch):
    """One key: the guess the pipeline hands to the masker and to the VO is the same object."""
    import numpy as np

    import mona_vo.masks as masks
    import mona_vo.pipeline as pipeline

    seen = {}
    real_masker, real_vo = masks.MonaMasker, pipeline.VisualOdometry

    def masker(config, intrinsics, **kw):
        seen["masks"] = intrinsics
        return real_masker(config, intrinsics, **kw)

    def vo(config, w, h, intrinsics, **kw):
        seen.setdefault("vo", intrinsics)   # the first pass (a second one starts from its focal)
        return real_vo(config, w, h, intrinsics, **kw)

    monkeypatch.setattr(masks, "MonaMasker", masker)
    monkeypatch.setattr(pipeline, "VisualOdometry", vo)
    from data_tools.synthetic import SceneConfig, SyntheticScene

    scene = SyntheticScene(SceneConfig(width=192, height=96, n_frames=6, preset="static", seed=0))

    class F:
        def __init__(self, r):
            self.index, self.timestamp, self.name, self.image = r.index, float(r.index), str(r.index), r.image

    cfg = load_config(PipelineConfig, None, {"assumed_hfov_deg": 90, "calibration.mode": "guess"})
    pipeline.estimate_trajectory([F(r) for r in scene], masks="mona", config=cfg)
    assert seen["masks"] == seen["vo"]
    assert seen["vo"].fx == pytest.approx(0.5 * 192 / np.tan(np.radians(45)))


def _versions(text: str) -> dict[str, str]:
    out = {}
    for line in text.splitlines():
        line = line.split("#")[0].strip()
        if "==" in line:
            name, version = line.split("==")
            out[name.strip().lower()] = version.strip()
    return out


def test_dependency_ranges_are_the_tested_versions():
    """pyproject.toml allows exactly the series constraints.txt installs (what CI tests)."""
    from packaging.requirements import Requirement

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    tested = _versions((ROOT / "constraints.txt").read_text())
    for dep in project["dependencies"]:
        req = Requirement(dep)
        name = req.name.lower()
        assert name in tested, f"{name} is not pinned in constraints.txt, so CI tests no fixed version of it"
        assert req.specifier.contains(tested[name]), f"{dep} excludes the tested {name}=={tested[name]}"
        assert not req.specifier.contains(_next_minor(tested[name])) or name in _RANGE_OK, \
            f"{dep} allows an untested series; pin it to {tested[name].rsplit('.', 1)[0]}.*"


# Libraries whose version cannot change a number mona-vo reports (plots, progress bars, YAML,
# image headers, the test runner): a major-version range is allowed for them.
_RANGE_OK = {"matplotlib", "pyyaml", "tqdm", "pillow", "pytest"}


def _next_minor(version: str) -> str:
    major, minor = version.split(".")[:2]
    return f"{major}.{int(minor) + 1}.0"

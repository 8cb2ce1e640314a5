"""Named speed/accuracy presets: config overrides applied before --config and --set.

Measured (README, Results, "Point density and the presets"): ``accurate`` is the denser point
grid of the map (the start keeps its own), chosen on the generator's tuning seeds and checked on
its held-out seeds, Bonn and the speed scenes; ``fast`` is older and its figures are in the same
section."""

PRESETS: dict[str, dict[str, object]] = {
    "default": {},
    # Fewer tracks and a shorter window: the VO 1.4x (fast turns) to 2x as fast, about 1.3x the
    # error on generated scenes.
    "fast": {"vo.grid_size": 12, "vo.window_keyframes": 6, "vo.ba.max_iterations": 5},
    # 24 x 24 new points per keyframe once a map exists instead of 16 x 16; the start keeps
    # 16 (with more far points its median parallax rises more slowly, and with 24 there too
    # the Bonn clip without masks built no map). Generated `mixed` scenes: ATE 1-26 % lower
    # with true masks, no masks and MONA masks on every part (geometric means); static 7-29 %
    # lower; the VO about half as fast on fast turns.
    # Not the default: on Bonn's long part the run without masks gains much more than MONA's
    # (README, Point density and the presets).
    "accurate": {"vo.grid_size": 24, "vo.init_grid_size": 16},
}


def preset_config(name: str, yaml_path=None, overrides: dict | None = None):
    """The configuration of preset ``name``: defaults, the preset, then the YAML file, then
    ``overrides`` (``--set``), checked once (:func:`mona_vo.config.load_config`). Every command
    that takes ``--preset`` builds its configuration here, so a preset means one thing."""
    from mona_vo.config import apply_overrides, load_config
    from mona_vo.pipeline import PipelineConfig

    return load_config(apply_overrides(PipelineConfig(), PRESETS[name]), yaml_path, overrides)

"""Named speed/accuracy presets: config overrides applied before --config and --set.

Measured (README, Results, "Point density and the presets"): ``accurate`` is the denser point
grid alone, chosen on the generator's tuning seeds and checked on its held-out seeds, Bonn and
the speed scenes; ``fast`` is older and its figures are in the same section."""

PRESETS: dict[str, dict[str, object]] = {
    "default": {},
    # Fewer tracks and a shorter window: the VO 1.4x (fast turns) to 2x as fast, about 1.3x the
    # error on generated scenes.
    "fast": {"vo.grid_size": 12, "vo.window_keyframes": 6, "vo.ba.max_iterations": 5},
    # 24 x 24 new points instead of 16 x 16: on generated static scenes and creeps about a
    # quarter lower ATE, the VO about half as fast. Not the default: with more far points the
    # start's median parallax rises more slowly, and the Bonn clip without masks builds no map.
    "accurate": {"vo.grid_size": 24},
}

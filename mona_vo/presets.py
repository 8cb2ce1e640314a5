"""Named speed/accuracy presets: config overrides applied before --config and --set."""

PRESETS: dict[str, dict[str, object]] = {
    "default": {},
    # Fewer tracks and a shorter window: about twice the VO speed, somewhat less accurate.
    "fast": {"vo.grid_size": 12, "vo.window_keyframes": 6, "vo.ba.max_iterations": 5},
    # More tracks and a longer window: slower, for offline runs that want the last millimetre.
    "accurate": {"vo.grid_size": 20, "vo.window_keyframes": 10, "vo.ba.max_iterations": 12},
}

"""mona-vo: camera trajectories of videos with moving people and cars.

MONA moving-object masks feed a LEAP-VO-style point-tracking visual odometry whose sliding-window
bundle adjustment (a GTSAM factor graph) drops every observation inside a moving-object mask.
Conventions (poses, quaternions, pixels) are in :mod:`mona_vo.conventions`.
"""
__version__ = "0.1.0"

from mona_vo.errors import BackendError, ConfigError, EvalError, InputError, MonaVoError  # noqa: F401

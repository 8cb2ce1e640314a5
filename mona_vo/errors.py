"""Exceptions of mona-vo. The CLI turns any :class:`MonaVoError` into one line and exit code 1;
anything else is a bug and keeps its traceback."""


class MonaVoError(Exception):
    """Base of every error mona-vo reports to its user."""


class InputError(MonaVoError):
    """An input file or folder is missing, unreadable or malformed. The message names the file."""


class ConfigError(MonaVoError):
    """A configuration value, option or override is wrong. The message names the key."""


class BackendError(MonaVoError):
    """A back end (tracker, flow, detector, segmenter) cannot be built, e.g. a missing checkpoint."""


class EvalError(MonaVoError):
    """An evaluation cannot be computed (e.g. no timestamps in common between GT and estimate)."""

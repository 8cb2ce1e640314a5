"""Back ends chosen by name, like evo's metrics or OpenCV's algorithms.

Each back-end kind (tracker, flow, detector, segmenter) owns one :class:`Registry`. Classes
register under a name; configs refer to them by that name, checked when the config loads.
Neural back ends register a *loader* path so that importing mona-vo never imports torch.
"""
from __future__ import annotations

import importlib
from typing import Callable

from mona_vo.errors import ConfigError


class Registry:
    def __init__(self, kind: str):
        self.kind = kind
        self._entries: dict[str, Callable | str] = {}

    def register(self, name: str, target: Callable | str | None = None):
        """Register ``target`` (a class, or ``"module:attr"`` imported on first use) under ``name``.
        Used bare as a class decorator when ``target`` is omitted."""
        if target is not None:
            self._entries[name] = target
            return target

        def deco(cls):
            self._entries[name] = cls
            return cls
        return deco

    def names(self) -> list[str]:
        return sorted(self._entries)

    def check(self, name: str) -> None:
        if name not in self._entries:
            raise ConfigError(f"unknown {self.kind} '{name}'; choose one of: {', '.join(self.names())}")

    def get(self, name: str) -> Callable:
        self.check(name)
        target = self._entries[name]
        if isinstance(target, str):
            module, attr = target.split(":")
            target = getattr(importlib.import_module(module), attr)
            self._entries[name] = target
        return target

    def create(self, name: str, **kwargs):
        return self.get(name)(**kwargs)

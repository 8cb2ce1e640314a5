"""The variants the harness runs each sequence with: the paper's ablations as config overrides
(no masks, MONA with box prompts, with point prompts, with the raw boxes, the true masks). Light
on imports, so that the commands check `--variants` before loading the pipeline."""
from __future__ import annotations

from typing import TYPE_CHECKING, Iterable

from mona_vo.config import apply_overrides
from mona_vo.errors import ConfigError

if TYPE_CHECKING:
    from mona_vo.pipeline import PipelineConfig

# name -> (where the masks come from: None, "mona" or "gt"; the config keys it sets)
VARIANTS = {
    "none": (None, {}),
    "mona": ("mona", {"masks.prompt": "boxes"}),
    "mona-points": ("mona", {"masks.prompt": "points"}),
    "mona-raw-boxes": ("mona", {"masks.prompt": "raw-boxes"}),
    "gt": ("gt", {}),
}


def parse_variants(text: str | Iterable[str]) -> list[str]:
    names = [v.strip() for v in (text.split(",") if isinstance(text, str) else text) if v.strip()]
    unknown = [v for v in names if v not in VARIANTS]
    if unknown or not names:
        raise ConfigError(f"unknown variant(s) {', '.join(unknown) or '(none given)'}; choose from: "
                          f"{', '.join(VARIANTS)}")
    return names


def variant_config(config: PipelineConfig, variant: str) -> PipelineConfig:
    return apply_overrides(config, VARIANTS[variant][1])

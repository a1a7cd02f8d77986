"""SSD matching (paper eq. 6) and R_k (eqs. 8-10). Settings only for now; lands with the CLF."""

from __future__ import annotations

from pydantic import Field

from condtrack_cli.config import StageSettings
from condtrack_cli.registry import register


class SSDSettings(StageSettings):
    template: int = Field(11, ge=3, le=63, description="side of the reference patch (px, odd)")


@register("measure", "ssd", SSDSettings, "SSD matching with R_k from the correlation surface")
def make_ssd(settings: SSDSettings):
    return settings

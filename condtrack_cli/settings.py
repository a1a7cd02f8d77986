"""The base of every stage's settings model (pydantic), apart from the config that fills them.

Stages import this module, never ``condtrack_cli.config``: a stage is handed its
validated settings and the objects it works with (``pipeline.py`` builds them).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import BaseModel, ConfigDict


class StageSettings(BaseModel):
    """Base of every stage's settings: frozen, strict types, unknown keys and non-finite numbers refused.

    ``frame_windows`` names the fields that are window sides in pixels and must
    fit in the frame; :meth:`condtrack_cli.config.Config.check_fits_frame` checks
    them once the frame size is known. ``filter_sections`` (a filter's settings
    only) names the other filters whose ``filter.<name>`` settings it reads, as
    the router ``auto`` reads ``clf`` and ``cnlf``; ``covariance`` (a filter's
    settings only) is False for a filter that writes no covariance (NaN), as
    STK: ``output.max_std`` then changes nothing.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)
    frame_windows: ClassVar[tuple[str, ...]] = ()
    filter_sections: ClassVar[tuple[str, ...]] = ()
    covariance: ClassVar[bool] = True

"""The base of every stage's settings model (pydantic), apart from the config that fills them.

Stages import this module, never ``condtrack_cli.config``: a stage is handed its
validated settings and the objects it works with (``pipeline.py`` builds them).
"""

from __future__ import annotations

import types
import typing
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, ValidationInfo, field_validator, model_validator


#: The largest value OpenCV takes for an ``int`` parameter (a C int); the bound of every integer setting handed to one.
OPENCV_INT_MAX = 2**31 - 1

#: The largest magnitude of a float setting: the trackers square and multiply them (1e200 squared overflows float64,
#: a traceback), and none is meaningful near it (pixels, px^2, grey levels, ratios). It also keeps
#: ``goodFeaturesToTrack``'s ``minDistance``, a float OpenCV rounds to a C int, below ``OPENCV_INT_MAX`` (3e9 crashed
#: the process).
MAX_FLOAT_SETTING = 1e9


class StageSettings(BaseModel):
    """Base of every stage's settings: frozen, strict types, unknown keys, non-finite numbers and floats beyond
    ``MAX_FLOAT_SETTING`` refused.

    A whole number written with an exponent (``1e3``, which YAML, ``--set`` and
    Python read as the float 1000.0) is taken for an integer key; a fractional
    one (``2.5``) is still refused there.

    ``frame_windows`` names the fields that are window sides in pixels and must
    fit in the frame; :meth:`condtrack_cli.config.Config.check_fits_frame` checks
    them once the frame size is known. ``filter_sections`` (a filter's settings
    only) names the other filters whose ``filter.<name>`` settings it reads, as
    the router ``auto`` reads ``clf`` and ``cnlf``; ``covariance`` (a filter's
    settings only) is False for a filter that writes no covariance (NaN), as
    STK: ``output.max_std`` then changes nothing. ``stage_kinds`` (a filter's settings only) names the stage kinds
    whose settings it reads (STK measures by its own Lucas-Kanade: neither ``motion`` nor ``measure``), so that only
    their windows must fit the frame. ``smoother`` (a filter's settings only) names the two-way smoother its tracker's
    ``smooth`` runs, "" when it has none: ``filter.smooth`` is then refused when the config is read, before any
    input is opened or output made. ``unbounded_floats`` names the float fields that only compare
    (a threshold such as ``output.max_std``, where 1e16 means "never"), exempt from ``MAX_FLOAT_SETTING``;
    ``odd_fields`` the integer fields that must be odd (patch sides with a centre pixel; null passes).
    ``extras`` (a filter's settings only) names the optional datasets its tracker can write, each switched on by
    ``output.store_<name>`` (``particles``: the CNLF's; ``segmentation``: ``auto``'s): the switch of one it does
    not write gets a warning when the config is read.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)
    frame_windows: ClassVar[tuple[str, ...]] = ()
    filter_sections: ClassVar[tuple[str, ...]] = ()
    covariance: ClassVar[bool] = True
    stage_kinds: ClassVar[tuple[str, ...]] = ("motion", "measure")
    smoother: ClassVar[str] = ""
    unbounded_floats: ClassVar[tuple[str, ...]] = ()
    odd_fields: ClassVar[tuple[str, ...]] = ()
    extras: ClassVar[tuple[str, ...]] = ()

    def least_longer_side(self) -> int:
        """The shortest longer side (px) of a frame this stage can run on (1: any; OpenCV's DIS needs 12)."""
        return 1

    @field_validator("*", mode="after")
    @classmethod
    def _within_bounds(cls, value: Any, info: ValidationInfo) -> Any:
        """``value``, refused when a float beyond ``MAX_FLOAT_SETTING`` in magnitude (``unbounded_floats`` aside) or
        an even number in one of ``odd_fields``."""
        if isinstance(value, float) and abs(value) > MAX_FLOAT_SETTING and info.field_name not in cls.unbounded_floats:
            raise ValueError(f"must be at most {MAX_FLOAT_SETTING:g} in magnitude")
        if info.field_name in cls.odd_fields and value is not None and value % 2 == 0:
            raise ValueError("must be odd")
        return value

    @model_validator(mode="before")
    @classmethod
    def _whole_floats_as_integers(cls, data: Any) -> Any:
        """``data`` with every finite whole float given to an integer field made an int (class docstring)."""
        if not isinstance(data, dict):
            return data
        return {key: int(value) if _is_whole_float(value) and _takes_integer(cls, key) else value
                for key, value in data.items()}


def _is_whole_float(value: Any) -> bool:
    """True for a finite float with no fractional part (``1e3``), False for anything else (bools and ints too)."""
    return isinstance(value, float) and value.is_integer()


def _takes_integer(model: type[BaseModel], key: Any) -> bool:
    """True where ``model``'s field ``key`` is an ``int`` or an optional one (``int | None``) and takes no float."""
    field = model.model_fields.get(key) if isinstance(key, str) else None
    if field is None:
        return False
    annotation = field.annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        members = set(typing.get_args(annotation))
        return int in members and float not in members
    return annotation is int

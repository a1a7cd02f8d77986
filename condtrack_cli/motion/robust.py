"""Robust parametric motion (paper §5.1). Settings only for now; the estimator lands with the CLF."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from condtrack_cli.config import StageSettings
from condtrack_cli.registry import register


class RobustMotionSettings(StageSettings):
    model: Literal["translation", "affine", "quadratic"] = Field("affine", description="parametric motion model")
    robust_cost: Literal["tukey", "geman_mcclure", "cauchy"] = Field("tukey", description="robust cost rho")
    levels: int = Field(4, ge=1, le=8, description="Gaussian pyramid levels, coarse to fine")
    iterations: int = Field(5, ge=1, le=50, description="warp + IRLS iterations per level")
    q_floor: float = Field(0.25, gt=0, description="floor added to the state noise Q_k (px^2)")
    local_window: int = Field(32, ge=8, description="side of the local support window (px)")


@register("motion", "robust", RobustMotionSettings, "robust parametric motion, coarse to fine with IRLS")
def make_robust_motion(settings: RobustMotionSettings):
    return settings

"""The registered motion stages ``dis`` (default), ``robust`` and ``regression`` (the paper's, issue 29): the global fit, the local field and Q_k, from one settings model each."""

from __future__ import annotations

from condtrack_cli.motion.dense import DenseFlow, DisGlobalMotion, DisLocalMotion, DisMotionSettings
from condtrack_cli.motion.interface import MotionStages
from condtrack_cli.motion.local import LocalMotion
from condtrack_cli.motion.regression import RegressionMotion, RegressionSettings
from condtrack_cli.motion.robust import GlobalMotion, RobustMotionSettings
from condtrack_cli.motion.state_noise import StateNoise
from condtrack_cli.registry import register


@register("motion", "robust", RobustMotionSettings, "robust parametric motion, coarse to fine with IRLS")
def make_robust_motion(settings: RobustMotionSettings, **_context) -> MotionStages:
    """Robust parametric motion: global support (``robust.py``), local support (``local/``), Q_k (``state_noise.py``)."""
    return MotionStages(
        global_motion=GlobalMotion(settings),
        local_motion=LocalMotion(settings),
        state_noise=StateNoise(settings.q_floor, settings.q_misfit, settings.misfit_window),
    )


@register("motion", "dis", DisMotionSettings, "one dense DIS field per frame pair: local motion, its spread, the global fit")
def make_dis_motion(settings: DisMotionSettings, **_context) -> MotionStages:
    """Dense inverse search (``dense.py``): the field shared by the global fit and the local motion; Q_k (``state_noise.py``)."""
    flow = DenseFlow(settings)
    return MotionStages(
        global_motion=DisGlobalMotion(settings, flow),
        local_motion=DisLocalMotion(settings, flow),
        state_noise=StateNoise(settings.q_floor, settings.q_misfit, settings.misfit_window),
    )


@register("motion", "regression", RegressionSettings,
          "the paper's: robust global fit, and a robust regression on the window around each position asked (slow)")
def make_regression_motion(settings: RegressionSettings, **_context) -> MotionStages:
    """Robust global fit (``robust.py``); the local motion regressed per position (``regression.py``); Q_k."""
    return MotionStages(
        global_motion=GlobalMotion(settings),
        local_motion=RegressionMotion(settings),
        state_noise=StateNoise(settings.q_floor, settings.q_misfit, settings.misfit_window),
    )

"""The filters: STK and MDR baselines, the conditional linear (CLF) and nonlinear (CNLF) filters."""

from condtrack_cli.filters import stk  # noqa: F401  (registers the stage)

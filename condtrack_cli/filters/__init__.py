"""The filters: STK and MDR baselines, the conditional linear (CLF) and nonlinear (CNLF) filters."""

from condtrack_cli.filters import clf, stk  # noqa: F401  (register the stages)

"""The filters: STK and MDR baselines, the conditional linear (CLF) and nonlinear (CNLF) filters, and ``auto``."""

from condtrack_cli.filters import auto, clf, cnlf, stk  # noqa: F401  (register the stages)

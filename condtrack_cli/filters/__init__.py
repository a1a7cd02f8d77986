"""The filters: STK and MDR baselines, the conditional linear (CLF) and nonlinear (CNLF) filters, and ``auto``.

Imports nothing: a run imports the stages it uses and no other (``registry.py``).
"""

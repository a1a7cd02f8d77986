"""Measurement: SSD matching in the validation gate and R_k from the correlation surface (§5.2)."""

from condtrack_cli.measure import ssd  # noqa: F401  (registers the stage)

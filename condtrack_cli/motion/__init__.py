"""Robust parametric motion estimation (paper §5.1)."""

from condtrack_cli.motion import stage  # noqa: F401  (registers the stage)

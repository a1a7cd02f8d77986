"""Robust parametric motion estimation (paper §5.1)."""

from condtrack_cli.motion import robust  # noqa: F401  (registers the stage)

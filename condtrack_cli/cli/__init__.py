"""The ``condtrack`` command line (console script ``condtrack = condtrack_cli.cli:main``)."""

from condtrack_cli.cli.track import cli, main  # noqa: F401

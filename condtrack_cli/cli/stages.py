"""``condtrack stages``: the registered stages per kind, or the default config."""

from __future__ import annotations

import click

from condtrack_cli import registry


@click.command("stages")
@click.option("--default-config", is_flag=True, help="Print the default configuration as commented YAML.")
def stages(default_config: bool) -> None:
    """List the registered stages per kind (built-in and from entry points)."""
    if default_config:
        from condtrack_cli.config import default_yaml

        click.echo(default_yaml(), nl=False)
        return
    for kind in registry.KINDS:
        click.echo(f"{kind}:")
        for name in registry.names(kind):
            click.echo(f"  {name:12s} {registry.get(kind, name).summary}")

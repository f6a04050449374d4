"""``swarm-sitl``: the PX4-like autopilot mock (issue #5). Not built yet: the command says so
and exits with status 2, rather than pretending to run vehicles."""

from __future__ import annotations

import click


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """PX4-like autopilot fleet speaking MAVLink (not available yet)."""
    raise click.ClickException(
        "the SITL autopilot mock is not implemented yet (tracked as issue #5); "
        "use `swarm-gcs sim` for the fast-time simulation"
    )

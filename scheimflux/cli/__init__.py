"""The `scheimflux` command: one subcommand per module in this folder."""

from ._main import main as main

__all__ = [
    "main",
]

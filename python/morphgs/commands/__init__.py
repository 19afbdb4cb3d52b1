"""Subcommands of the `morphgs` CLI (see morphgs.cli)."""

"""Subcommands of the ``onfly`` CLI, one module each (see :mod:`onfly.cli`)."""

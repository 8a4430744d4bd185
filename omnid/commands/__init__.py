"""Subcommands of the ``omnid`` command line, one module each (see :mod:`omnid.cli`)."""

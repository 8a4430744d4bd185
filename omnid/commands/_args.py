"""Option types shared by the subcommands: a number that is no number (``nan``, ``inf``) or
out of range is refused by the parser in one line naming the option, before anything runs."""

from __future__ import annotations

import argparse
import math


def finite_float(text: str) -> float:
    """A finite number (mm, s), for an option that may be zero or negative."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number greater than zero (a length in mm, a duration in s)."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return value

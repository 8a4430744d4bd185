"""``omnid experiment table72 [--variant pixels|detected] [--seed N]`` — reproduce thesis Table 7.2.

Prints Markdown tables: for ``pixels`` the thesis' layout (per plane and weighted, X/Y/Z mean
relative error for each noise column) with the thesis' numbers in brackets, for the thesis'
triangulation and ours; for ``detected`` the rendered-capture pipeline comparison (mean absolute
error per axis, mm). See :mod:`omnid.experiments.table72`.
"""

from __future__ import annotations

import argparse
from typing import Any


def _table72(args: argparse.Namespace) -> int:
    from omnid.errors import InputError
    from omnid.experiments import table72

    if not args.grid_step_mm > 0:
        raise InputError(f"--grid-step-mm must be positive, got {args.grid_step_mm}")
    if args.variant == "pixels":
        result = table72.run_pixels(seed=args.seed, grid_step_mm=args.grid_step_mm)
        text = table72.format_pixels(result)
    else:
        detected = table72.run_detected(seed=args.seed, grid_step_mm=args.grid_step_mm)
        text = table72.format_detected(detected)
    print(text)
    return 0


def register(subparsers: Any) -> None:
    """Add ``omnid experiment`` and its experiments to the CLI."""
    parser = subparsers.add_parser(
        "experiment",
        help="reproduce the thesis' experiments (Table 7.2)",
        description="Reproduce the thesis' experiments and print their tables (Markdown).",
    )
    experiments = parser.add_subparsers(dest="experiment", metavar="EXPERIMENT", required=True)
    t72 = experiments.add_parser(
        "table72",
        help="synthetic planes 400-1100 mm: triangulation error rates (thesis Table 7.2)",
        description=(
            "Thesis Table 7.2: eight horizontal planes 400-1100 mm below the mirrors, points on a "
            "grid, integer pixel positions, then U(-1, 1) noise on r1, c1, r2, c2 in turn. "
            "'pixels' reproduces the table for the thesis' triangulation and ours; 'detected' "
            "renders the dots, detects and triangulates them with each method."
        ),
    )
    t72.add_argument("--variant", choices=["pixels", "detected"], default="pixels")
    t72.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    t72.add_argument(
        "--grid-step-mm", type=float, default=100.0, help="grid spacing on each plane (default 100)"
    )
    t72.set_defaults(func=_table72)

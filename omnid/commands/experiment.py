"""``omnid experiment table72 [--variant pixels|detected] [--seed N]`` — reproduce thesis Table 7.2;
``omnid experiment table74 [--seed N] [--planes ...] [--rig misaligned|nominal]`` — Table 7.4
(:mod:`omnid.experiments.table74`).

Prints Markdown tables: for ``pixels`` the thesis' layout (per plane and weighted, X/Y/Z mean
relative error for each noise column) with the thesis' numbers in brackets, for the thesis'
triangulation and ours; for ``detected`` the rendered-capture pipeline comparison (mean absolute
error per axis, mm). See :mod:`omnid.experiments.table72`.
"""

from __future__ import annotations

import argparse
from typing import Any

from omnid.commands._args import positive_float


def _table72(args: argparse.Namespace) -> int:
    from omnid.experiments import table72

    if args.variant == "pixels":
        result = table72.run_pixels(seed=args.seed, grid_step_mm=args.grid_step_mm)
        text = table72.format_pixels(result)
    else:
        detected = table72.run_detected(seed=args.seed, grid_step_mm=args.grid_step_mm)
        text = table72.format_detected(detected)
    print(text)
    return 0


def _table74(args: argparse.Namespace) -> int:
    from omnid.errors import InputError
    from omnid.experiments import table74

    known = table74.plane_names()
    names = known if args.planes is None else [n for n in args.planes.split(",") if n]
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise InputError(
            f"--planes: unknown layout {unknown or names!r} (known: {', '.join(known)})"
        )
    calib, rig, results = table74.run_table74(
        seed=args.seed, names=names, misaligned=args.rig == "misaligned"
    )
    print(table74.format_table74(calib, rig, results))
    return 0


def register(subparsers: Any) -> None:
    """Add ``omnid experiment`` and its experiments to the CLI."""
    parser = subparsers.add_parser(
        "experiment",
        help="reproduce the thesis' experiments (Tables 7.2, 7.4)",
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
        "--grid-step-mm",
        type=positive_float,
        default=100.0,
        help="grid spacing on each plane (default 100)",
    )
    t72.set_defaults(func=_table72)
    t74 = experiments.add_parser(
        "table74",
        help="horizontal and vertical planes: error distributions per method (thesis Table 7.4)",
        description=(
            "Thesis Table 7.4: a horizontal plane 680/800/930/1100 mm below the mirrors and a "
            "vertical plane 550-1750 mm ahead, rendered with misaligned cameras; the rig is "
            "calibrated on the empty floor, each layout perceived with each method (its own "
            "detector, matching, triangulation). Prints the error distribution of the plane's "
            "axis beside the thesis' numbers, per-axis means (Table 7.5) and matched / wrong / "
            "classified."
        ),
    )
    t74.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    t74.add_argument(
        "--planes",
        default=None,
        help="comma-separated layouts (default: all ten, e.g. vertical_550)",
    )
    t74.add_argument(
        "--rig",
        choices=["misaligned", "nominal"],
        default="misaligned",
        help="misaligned cameras (default) or the nominal, perfectly aligned rig",
    )
    t74.set_defaults(func=_table74)

"""Thin wrapper: ``python tools/table72.py [--variant pixels|detected] [--seed N]``.

Same as ``omnid experiment table72 ...``; prints the Markdown tables of thesis Table 7.2.
"""

from __future__ import annotations

import sys

from omnid.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "table72", *sys.argv[1:]]))

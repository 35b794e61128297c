#!/usr/bin/env python
"""Kept for old instructions: forwards to ``ffrecon export-model dust3r|mast3r`` (the user command).

    python tools/export_dust3r_onnx.py [--family dust3r|mast3r] --upstream DIR --checkpoint FILE.pth -o OUT.onnx

``--family`` picks the family (default dust3r), ``--batch N`` is read as ``--frames N``; every other
option is ``ffrecon export-model``'s (``ffrecon export-model --help``; docs/models.md).
"""

from __future__ import annotations

import sys

from ffrecon.cli import main as ffrecon_main


def translate(argv: list[str]) -> list[str]:
    """This script's arguments as ``ffrecon export-model`` arguments.

    >>> translate(["--family", "mast3r", "--batch", "3", "--out", "m.onnx"])
    ['export-model', 'mast3r', '--frames', '3', '--out', 'm.onnx']
    """
    family, rest, args = "dust3r", [], iter(argv)
    for arg in args:
        if arg == "--family":
            family = next(args, family)
        elif arg.startswith("--family="):
            family = arg.split("=", 1)[1]
        else:
            rest.append("--frames" if arg == "--batch" else arg)
    return ["export-model", family, *rest]


if __name__ == "__main__":
    sys.exit(ffrecon_main(translate(sys.argv[1:])))

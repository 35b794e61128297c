#!/usr/bin/env python
"""Kept for old instructions: forwards to ``ffrecon export-model vggt`` (the user command).

    python tools/export_vggt_onnx.py --upstream DIR --checkpoint model.pt -o OUT.onnx

Every option is ``ffrecon export-model``'s (``ffrecon export-model --help``; docs/models.md).
"""

from __future__ import annotations

import sys

from ffrecon.cli import main as ffrecon_main

if __name__ == "__main__":
    sys.exit(ffrecon_main(["export-model", "vggt", *sys.argv[1:]]))

from ffrecon.cli import entry

raise SystemExit(entry())

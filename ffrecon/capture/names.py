"""Photo names every later stage can use: checked on the file list, before any photo is decoded.

Two rules, both refused with the names at fault (exit 2):

- **No two photos may share a stem or a name once letter case is ignored.** Outputs are named by
  stem (``feedforward/depth/<stem>.npz``; masks are looked up as ``<stem>.png`` or ``<name>.png``), so
  ``a.jpg`` and ``a.png`` would write the same files; and on case-insensitive file systems (macOS,
  Windows) ``b.JPG`` and ``b.jpg`` are one file. A photo's keys are its stem and its name, case-folded;
  two photos clash when they share a key (``a.jpg`` and ``a.jpg.png`` too: ``a.jpg.png`` is the mask
  name of both).
- **No white space in a name.** COLMAP's pair lists (``name1 name2`` a line, read by the cross-check
  and the refinement's matching) and its text model format split on white space.

Video frames are named by ffrecon (``<video stem>_<frame index>.png``, white space made ``_``), so
they always pass.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from ffrecon.errors import InputError

_LISTED = 4  # clashing groups named in the message; the rest are counted


def _keys(name: str) -> set[str]:
    return {Path(name).stem.casefold(), name.casefold()}


def name_clashes(names: Sequence[str]) -> list[list[str]]:
    """Groups of names that share a stem or a name, ignoring case (in the order given).

    >>> name_clashes(["a.jpg", "a.png", "b.JPG", "b.jpg", "c.jpg"])
    [['a.jpg', 'a.png'], ['b.JPG', 'b.jpg']]
    """
    group_of: dict[str, int] = {}
    groups: list[list[str]] = []
    for name in names:
        found = sorted({group_of[k] for k in _keys(name) if k in group_of})
        if not found:
            groups.append([name])
            target = len(groups) - 1
        else:  # join this name, and any groups it bridges, into the first group it clashes with
            target = found[0]
            groups[target].append(name)
            for other in found[1:]:
                groups[target] += groups[other]
                groups[other] = []
                group_of.update({k: target for n in groups[target] for k in _keys(n)})
        group_of.update({k: target for k in _keys(name)})
    return [g for g in groups if len(g) > 1]


def check_names(names: Sequence[str], folder: Path) -> None:
    """Raise :class:`InputError` (one line: the names at fault and the fix) when ``names`` (the photos of
    ``folder`` that will be used) hold white space or clash (see the module's docstring)."""
    spaced = [n for n in names if any(c.isspace() for c in n)]
    if spaced:
        listed = ", ".join(repr(n) for n in spaced[:_LISTED]) + (" ..." if len(spaced) > _LISTED else "")
        raise InputError(
            f"{len(spaced)} photo name(s) in {folder} contain white space ({listed}); "
            "COLMAP's pair lists and text models cannot hold them",
            "rename the photos without spaces (e.g. `rename 's/\\s+/_/g' *`)",
        )
    clashes = name_clashes(names)
    if clashes:
        listed = "; ".join(" and ".join(g) for g in clashes[:_LISTED])
        more = f"; and {len(clashes) - _LISTED} more" if len(clashes) > _LISTED else ""
        raise InputError(
            f"{sum(map(len, clashes))} photos in {folder} share a name once the extension and letter case are "
            f"ignored ({listed}{more}); their outputs (depth, masks) are named by that and would overwrite each other",
            "rename them so that every photo has its own name without its extension, e.g. a.png -> a_2.png",
        )

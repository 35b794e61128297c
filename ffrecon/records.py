"""Typed records: a stage's result as JSON plus one ``.npz`` of its arrays, read back without running code.

A record is strict JSON. Numbers, strings, booleans, null and lists stand for themselves; every JSON
object is one tagged value, named by its one ``$`` key:

- ``{"$dataclass": "ffrecon.types:PinholeCamera", "fx": ..., ...}``: a dataclass of ffrecon, by module and
  qualified name, with the fields its ``__init__`` takes;
- ``{"$enum": "ffrecon.sfm.crosscheck.gate_types:GateStatus", "name": "PASSED"}``: a member of an enum of ffrecon;
- ``{"$tuple": [...]}`` (a JSON list is a list); ``{"$dict": [[key, value], ...]}`` (keys of any
  stored kind: ``PoseErrors.auc`` is keyed by int thresholds);
- ``{"$path": "<run>/images"}``; ``{"$float": "nan"}`` (also ``"inf"``, ``"-inf"``);
- ``{"$array": "a0", "dtype": "<f8", "shape": [12, 3, 4]}``: a numpy array, stored in the ``.npz`` under
  its name; ``{"$scalar": "a1", "dtype": "<f4"}``: a numpy scalar, stored as a 0-d array.

Reading constructs nothing else. A class is looked up by module and qualified name among the modules
of ffrecon already imported (never importing one: importing ``ffrecon.__main__`` runs the command
line), and must be a dataclass or an enum defined there; its stored fields must be those of its
``__init__`` now. Arrays are read with ``allow_pickle=False``. Anything else is a :class:`RecordError`.

>>> tree, arrays = encode({"up": np.zeros(3), 5: (Path("<run>/a.ply"), float("nan"))})
>>> tree["$dict"][0]
['up', {'$array': 'a0', 'dtype': '<f8', 'shape': [3]}]
>>> tree["$dict"][1]
[5, {'$tuple': [{'$path': '<run>/a.ply'}, {'$float': 'nan'}]}]
>>> decode(tree, arrays)
{'up': array([0., 0., 0.]), 5: (PosixPath('<run>/a.ply'), nan)}
>>> decode({"$dataclass": "subprocess:Popen", "args": ["touch", "x"]}, {})
Traceback (most recent call last):
ffrecon.records.RecordError: 'subprocess:Popen' is not a class of ffrecon; records construct nothing else
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
import os
import sys
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

FORMAT = 1  # the record format this code writes and reads; any change to the encoding bumps it
_FLOATS = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}
_SCALARS = (str, int, float, bool, type(None))  # JSON as they are (exact types: IntEnums, numpy floats are tagged)


class RecordError(ValueError):
    """A record that cannot be read: unreadable, truncated, of another format, or asking for what ffrecon
    does not construct. The stage it belongs to simply runs again."""


class RecordFormatError(RecordError):
    """A record written in another record format (by an earlier or later version of ffrecon)."""


# -- files ------------------------------------------------------------------------------------------


def write_record(record: Path, arrays_path: Path, meta: dict, result: object) -> None:
    """Write ``result`` and ``meta`` as ``record`` (JSON, written last) and ``arrays_path`` (``.npz``).

    Each file is written under a temporary name and moved into place, so a record that exists is whole.
    Raises :class:`RecordError` when ``result`` holds something that is not data (nothing is written).
    """
    tree, arrays = encode(result)
    text = json.dumps({"format": FORMAT, **meta, "result": tree}, indent=1, allow_nan=False)
    record.parent.mkdir(parents=True, exist_ok=True)
    if arrays:
        _replace(arrays_path, lambda fh: np.savez(fh, **arrays))
    else:
        arrays_path.unlink(missing_ok=True)
    _replace(record, lambda fh: fh.write(text.encode()))


def _replace(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_meta(record: Path) -> dict:
    """The JSON of ``record`` (its key, seconds, options, inputs and encoded result), of this format.

    Raises :class:`RecordFormatError` for a record of another format (records before format 1 held a
    pickle beside them, which is never read), :class:`RecordError` when it is not a record at all.
    """
    try:
        meta = json.loads(record.read_bytes(), parse_constant=_refuse_constant)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise RecordError(f"{record.name} is not valid JSON ({err})") from None
    if not isinstance(meta, dict):
        raise RecordError(f"{record.name} is not a record (a JSON {type(meta).__name__})")
    found = meta.get("format")
    if found != FORMAT:
        was = "a pickled result, which is never read" if found is None else f"record format {found!r}"
        raise RecordFormatError(f"written by another version of ffrecon ({was}; this version reads format {FORMAT})")
    if "result" not in meta:
        raise RecordError(f"{record.name} holds no result")
    return meta


def _refuse_constant(name: str):
    raise RecordError(f"{name} is not JSON (records write non-finite numbers as {{'$float': ...}})")


def read_result(meta: dict, arrays_path: Path) -> object:
    """Decode the result of a record read by :func:`read_meta`, its arrays from ``arrays_path``."""
    if not arrays_path.is_file():
        return decode(meta["result"], {})
    try:
        arrays = np.load(arrays_path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise RecordError(f"{arrays_path.name} cannot be read ({err})") from None
    if not isinstance(arrays, np.lib.npyio.NpzFile):
        raise RecordError(f"{arrays_path.name} is not an .npz archive")
    with arrays:
        return decode(meta["result"], arrays)


# -- encoding ---------------------------------------------------------------------------------------


def encode(obj: object) -> tuple[object, dict[str, np.ndarray]]:
    """``(tree, arrays)``: ``obj`` as JSON-ready values, and the numpy arrays it references by name.

    Raises :class:`RecordError` naming the first value that is not data (a pycolmap object, a callable,
    a torch tensor, an object array, a class outside ffrecon).
    """
    arrays: dict[str, np.ndarray] = {}
    return _encode(obj, arrays, "result"), arrays


def _encode(obj, arrays: dict, where: str):
    kind = type(obj)
    if isinstance(obj, enum.Enum):
        return {"$enum": _class_name(kind, where), "name": obj.name}
    if kind is float and not math.isfinite(obj):
        return {"$float": repr(obj)}
    if kind in _SCALARS:
        return obj
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        fields = {f.name: _encode(getattr(obj, f.name), arrays, f"{where}.{f.name}") for f in _init_fields(kind)}
        return {"$dataclass": _class_name(kind, where), **fields}
    if kind is tuple:
        return {"$tuple": [_encode(v, arrays, f"{where}[{k}]") for k, v in enumerate(obj)]}
    if kind is list:
        return [_encode(v, arrays, f"{where}[{k}]") for k, v in enumerate(obj)]
    if kind is dict:
        return {"$dict": [[_encode(k, arrays, where), _encode(v, arrays, f"{where}[{k!r}]")] for k, v in obj.items()]}
    if isinstance(obj, Path):
        return {"$path": str(obj)}
    if kind is np.ndarray or isinstance(obj, np.generic):
        array = np.asarray(obj)
        if array.dtype.hasobject:
            raise RecordError(f"{where}: a numpy array of Python objects is not data")
        name = f"a{len(arrays)}"
        arrays[name] = array
        if kind is np.ndarray:
            return {"$array": name, "dtype": array.dtype.str, "shape": list(array.shape)}
        return {"$scalar": name, "dtype": array.dtype.str}
    raise RecordError(f"{where}: a {kind.__module__}.{kind.__qualname__} is not data a record can hold")


def _init_fields(cls: type) -> list[dataclasses.Field]:
    """The fields ``__init__`` takes (``init=False`` fields are derived by the class itself)."""
    return [f for f in dataclasses.fields(cls) if f.init]


def _class_name(cls: type, where: str) -> str:
    name = f"{cls.__module__}:{cls.__qualname__}"
    try:
        found = _ffrecon_class(name)
    except RecordError as err:
        raise RecordError(f"{where}: {err}") from None
    if found is not cls:
        raise RecordError(f"{where}: {name} does not name the class {cls!r}")
    return name


# -- decoding ---------------------------------------------------------------------------------------


def decode(tree: object, arrays: Mapping[str, np.ndarray]) -> object:
    """The value :func:`encode` made ``tree`` from (``arrays``: its arrays by name, e.g. an open ``.npz``).

    Raises :class:`RecordError` for anything that is not such a tree; constructs nothing else.
    """
    try:
        return _decode(tree, arrays)
    except RecordError:
        raise
    except (KeyError, TypeError, ValueError, OSError, EOFError, zipfile.BadZipFile, RecursionError) as err:
        raise RecordError(f"the record does not decode ({type(err).__name__}: {err})") from None


def _decode(node, arrays: Mapping[str, np.ndarray]):
    if type(node) in _SCALARS:
        return node
    if type(node) is list:
        return [_decode(v, arrays) for v in node]
    if type(node) is not dict:
        raise RecordError(f"a {type(node).__name__} is not a record value")
    tags = [k for k in node if k.startswith("$")]
    if len(tags) != 1:
        raise RecordError(f"a record object needs one '$' tag, this one has {tags}")
    tag, value = tags[0], node[tags[0]]
    if tag == "$dataclass":
        return _decode_dataclass(value, {k: v for k, v in node.items() if k != tag}, arrays)
    _expect_keys(node, tag, {"$enum": {"name"}, "$array": {"dtype", "shape"}, "$scalar": {"dtype"}}.get(tag, set()))
    if tag == "$enum":
        cls = _ffrecon_class(value)
        if not issubclass(cls, enum.Enum):
            raise RecordError(f"{value} is not an enum")
        return cls[node["name"]]
    if tag == "$tuple":
        return tuple(_decode(v, arrays) for v in _list(value, tag))
    if tag == "$dict":
        return {_decode(k, arrays): _decode(v, arrays) for k, v in (_pair(p) for p in _list(value, tag))}
    if tag == "$path":
        return Path(_string(value, tag))
    if tag == "$float":
        if value not in _FLOATS:
            raise RecordError(f"{value!r} is not a non-finite float")
        return _FLOATS[value]
    if tag in ("$array", "$scalar"):
        if _string(value, tag) not in arrays:
            raise RecordError(f"the record's .npz holds no array {value!r}")
        array = arrays[value]
        shape = node["shape"] if tag == "$array" else []
        if array.dtype.str != node["dtype"] or list(array.shape) != shape:
            found = f"{array.dtype.str} {list(array.shape)}"
            raise RecordError(f"array {value} is {found} in the .npz; the record says {node['dtype']} {shape}")
        return array if tag == "$array" else array[()]
    raise RecordError(f"unknown record tag {tag!r}")


def _decode_dataclass(name, values: dict, arrays: Mapping[str, np.ndarray]):
    cls = _ffrecon_class(name)
    if not dataclasses.is_dataclass(cls):
        raise RecordError(f"{name} is not a dataclass")
    expected = {f.name for f in _init_fields(cls)}
    if set(values) != expected:
        missing, extra = sorted(expected - set(values)), sorted(set(values) - expected)
        raise RecordError(f"{name} has other fields now (missing {missing}, unknown {extra})")
    kwargs = {k: _decode(v, arrays) for k, v in values.items()}
    try:
        return cls(**kwargs)
    except Exception as err:  # the class's own checks (__post_init__) refuse the stored values
        raise RecordError(f"{name} refuses the stored values ({type(err).__name__}: {err})") from None


def _ffrecon_class(name) -> type:
    """The dataclass or enum ``name`` (``module:qualname``) names, defined in an imported module of ffrecon.

    Looked up in the module's and classes' own ``__dict__`` (no ``__getattr__``, no descriptors run).
    """
    module_name, _, qualname = _string(name, "class").partition(":")
    if not (module_name == "ffrecon" or module_name.startswith("ffrecon.")):
        raise RecordError(f"{name!r} is not a class of ffrecon; records construct nothing else")
    module = sys.modules.get(module_name)
    if module is None:
        raise RecordError(f"{name!r}: module {module_name} is not loaded (records never import one)")
    found = module
    for part in qualname.split("."):
        found = vars(found).get(part)
        if found is None:
            raise RecordError(f"{name!r} names nothing in ffrecon now")
        if not isinstance(found, type):
            raise RecordError(f"{name!r} is not a class")
    is_data = dataclasses.is_dataclass(found) or issubclass(found, enum.Enum)
    if not is_data or found.__module__ != module_name or found.__qualname__ != qualname:
        raise RecordError(f"{name!r} is not a dataclass or enum defined in ffrecon")
    return found


def _expect_keys(node: dict, tag: str, others: set[str]) -> None:
    if set(node) != {tag, *others}:
        raise RecordError(f"a {tag} object has the keys {sorted(node)}, not {sorted({tag, *others})}")


def _list(value, tag: str) -> list:
    if type(value) is not list:
        raise RecordError(f"{tag} holds a {type(value).__name__}, not a list")
    return value


def _pair(value) -> list:
    if type(value) is not list or len(value) != 2:
        raise RecordError("a $dict item is not a [key, value] pair")
    return value


def _string(value, what: str) -> str:
    if type(value) is not str:
        raise RecordError(f"{what} names a {type(value).__name__}, not a string")
    return value

"""JSON of a run-log document whose parts that stand from push to push are encoded once.

A checkpoint holds the executor's whole state after every push: at 1000 objects some
600 kB of JSON, most of it what the checkpoint before held too (the believed objects not
seen since, their sightings, the swept areas of the last pushes, the replanner's base
environment), and encoding it anew took 13 ms a push. The state's owners hand such a
part out as the same :class:`Kept` dict or :class:`KeptList` for as long as its source
stands (:class:`PartCache` keeps them), and the part carries its JSON once encoded; the
containers on the way to kept parts are :class:`Parts` (a list) and :class:`PartsDict`
(a dict with str keys), which :func:`dumps` encodes item by item. Anything else is
``json.dumps``'s, and so are the bytes of the whole: a document without such parts is
encoded exactly as before.

A kept part must never change: its JSON is the one it had when first encoded.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from typing import Any

_SEP = (",", ":")


class Kept(dict):
    """A dict that never changes, carrying its JSON once encoded."""

    __slots__ = ("json",)


class KeptList(list):
    """A list that never changes, carrying its JSON once encoded."""

    __slots__ = ("json",)


class Parts(list):
    """A list some of whose items are kept parts."""


class PartsDict(dict):
    """A dict (str keys) some of whose values are kept parts, or containers of them."""


def kept(part: dict | list) -> Kept | KeptList:
    """``part`` (a dict or a list, never changed from now on) as a kept part."""
    out = Kept(part) if isinstance(part, dict) else KeptList(part)
    out.json = None
    return out


class PartCache:
    """The kept part made of each source, by key, for as long as the source stands: the
    same object (``is``), or an equal tuple of values."""

    def __init__(self) -> None:
        self._parts: dict[Any, tuple[Any, Any]] = {}

    def parts(self, items: Iterable[tuple[Any, Any]], make: Callable[[Any], dict | list]) -> list:
        """The parts of ``items`` (``(key, source)``), in order: kept as before where the
        source stands, else ``kept(make(source))``. Keys not among ``items`` are forgotten."""
        old, new, out = self._parts, {}, []
        for key, source in items:
            had = old.get(key)
            if had is None or not (had[0] is source or (type(source) is tuple and had[0] == source)):
                had = (source, kept(make(source)))
            new[key] = had
            out.append(had[1])
        self._parts = new
        return out


def dumps(doc: Any, default: Callable[[Any], Any] | None = None) -> str:
    """``json.dumps(doc, separators=(",", ":"), default=default)``, kept parts encoded once."""
    if isinstance(doc, (Kept, KeptList)):
        if doc.json is None:
            doc.json = json.dumps(doc, separators=_SEP, default=default)
        return doc.json
    if isinstance(doc, Parts):
        return "[" + ",".join([_json(x, default) for x in doc]) + "]"
    if isinstance(doc, PartsDict):
        return "{" + ",".join([_key(k) + ":" + _json(x, default) for k, x in doc.items()]) + "}"
    return json.dumps(doc, separators=_SEP, default=default)


def _json(x: Any, default) -> str:
    """:func:`dumps` of an item, a kept part's JSON taken as it is (a checkpoint's
    thousand parts, each without a further call)."""
    got = x.json if type(x) in _KEPT else None
    return got if got is not None else dumps(x, default)


_KEPT = (Kept, KeptList)
#: JSON of the keys seen (object ids: the same few thousand in every checkpoint).
_KEYS: dict[str, str] = {}


def _key(k: Any) -> str:
    k = str(k)
    got = _KEYS.get(k)
    if got is None:
        if len(_KEYS) >= 100_000:
            _KEYS.clear()
        got = _KEYS[k] = json.dumps(k)
    return got

"""JSON of a run-log document whose parts that stand from push to push are encoded once.

A checkpoint holds the executor's whole state after every push: at 1000 objects some
600 kB of JSON, most of it what the checkpoint before held too (the believed objects not
seen since, their sightings, the swept areas of the last pushes, the replanner's base
environment), and encoding it anew took 13 ms a push. The state's owners hand such a
part out as the same object for as long as it stands and mark it with :func:`kept`; the
containers on the way to kept parts are :class:`Parts` (a list) and :class:`PartsDict`
(a dict with str keys), which :func:`dumps` encodes item by item. Anything else is
``json.dumps``'s, and so are the bytes of the whole: a document without such parts is
encoded exactly as before.

A kept part must never change after it was marked: its JSON is the one it had then.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

#: Kept parts remembered at most (then forgotten at once, and each encoded again when
#: it comes next).
KEPT_MAX = 50_000
_SEP = (",", ":")
_kept: dict[int, list] = {}        # id -> [the part (held, so its id stays its own), its JSON or None]


class Parts(list):
    """A list some of whose items are kept parts."""


class PartsDict(dict):
    """A dict (str keys) some of whose values are kept parts, or containers of them."""


def kept(part: Any) -> Any:
    """Mark ``part`` (a dict or list that is never changed from now on) to be encoded
    once; returns it."""
    if id(part) not in _kept:
        if len(_kept) >= KEPT_MAX:
            _kept.clear()
        _kept[id(part)] = [part, None]
    return part


def dumps(doc: Any, default: Callable[[Any], Any] | None = None) -> str:
    """``json.dumps(doc, separators=(",", ":"), default=default)``, kept parts encoded once."""
    entry = _kept.get(id(doc))
    if entry is not None and entry[0] is doc:
        if entry[1] is None:
            entry[1] = _encode(doc, default)
        return entry[1]
    return _encode(doc, default)


def _encode(v: Any, default) -> str:
    if isinstance(v, Parts):
        return "[" + ",".join(dumps(x, default) for x in v) + "]"
    if isinstance(v, PartsDict):
        return "{" + ",".join(json.dumps(str(k)) + ":" + dumps(x, default) for k, x in v.items()) + "}"
    return json.dumps(v, separators=_SEP, default=default)

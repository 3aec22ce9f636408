"""Checkpoint JSON with the parts that stand from push to push encoded once
(``executor/json_parts.py``): the bytes are ``json.dumps``'s, checkpoint after checkpoint."""

from __future__ import annotations

import json

import numpy as np
from hypothesis import given, settings, strategies as st

from nanoasm.executor.json_parts import PartCache, Parts, PartsDict, dumps, kept
from nanoasm.executor.runlog import _plain, to_json

SEP = (",", ":")
leaves = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=True), st.text(max_size=5))
plain = st.recursive(leaves, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                     st.dictionaries(st.text(max_size=4), inner, max_size=4)),
                     max_leaves=12)


@st.composite
def documents(draw, depth=0):
    """Plain JSON values, kept parts, and Parts / PartsDict containers of them."""
    kind = draw(st.integers(0, 3 if depth < 3 else 0))
    if kind == 0:
        return draw(plain)
    if kind == 1:
        return kept(draw(st.one_of(st.lists(plain, max_size=3), st.dictionaries(st.text(max_size=3), plain,
                                                                               max_size=3))))
    if kind == 2:
        return Parts(draw(st.lists(documents(depth + 1), max_size=4)))
    return PartsDict(draw(st.dictionaries(st.text(max_size=4), documents(depth + 1), max_size=4)))


@settings(max_examples=200, deadline=None)
@given(documents())
def test_the_bytes_are_json_dumps_and_again_once_its_parts_are_kept(doc):
    want = json.dumps(doc, separators=SEP)
    assert dumps(doc) == want
    assert dumps(doc) == want                    # the kept parts' JSON reused


def test_a_kept_part_is_encoded_once_and_numpy_goes_through_the_default():
    part = kept({"cov": np.eye(2), "t": np.float64(1.5)})
    doc = PartsDict(a=Parts([part, part]), b=[1, 2])
    want = json.dumps(doc, separators=SEP, default=_plain)
    assert to_json(doc) == want.encode()
    assert part.json == json.dumps(part, separators=SEP, default=_plain)
    part.json = '"stale"'                         # what a changed kept part would log: it is never re-read
    assert to_json(doc).count(b'"stale"') == 2


def test_a_part_stands_while_its_source_does_and_unused_keys_are_forgotten():
    cache, made = PartCache(), []
    a, b = object(), object()

    def make(src):
        made.append(src)
        return {"n": len(made)}

    first = cache.parts([("a", a), ("v", (1.0, 2.0))], make)
    again = cache.parts([("a", a), ("v", (1.0, 2.0))], make)           # the same object, an equal tuple
    assert again[0] is first[0] and again[1] is first[1] and len(made) == 2
    moved = cache.parts([("a", b), ("v", (1.0, 2.5))], make)
    assert moved[0] is not first[0] and moved[1] is not first[1] and len(made) == 4
    cache.parts([("v", (1.0, 2.5))], make)
    assert cache.parts([("a", b)], make)[0] is not moved[0]            # "a" was forgotten, made again


def test_every_checkpoint_of_a_dry_run_logs_as_json_dumps_would():
    """A whole dry-run (objects pushed, seen, swept; a replan or not): each checkpoint,
    taken as the engine hands it to the log, encodes to json.dumps's bytes, so no kept
    part went stale between two checkpoints."""
    from nanoasm.dryrun import dry_run
    from nanoasm.executor.documents import CHECKPOINT, as_dict
    from nanoasm.executor.strategy import ExecOptions
    from nanoasm.world.families import family_case

    seen = []

    def check(topic, doc):
        if topic == CHECKPOINT:
            d = as_dict(doc)
            seen.append(d["t"])
            assert to_json(d) == json.dumps(d, separators=SEP, default=_plain).encode()

    scene, layout = family_case("tiny", 1)
    dry_run(scene, layout, options=ExecOptions(strategy="full"), subscribers=[check])
    assert len(seen) >= 3

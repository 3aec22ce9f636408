"""Run documents: every one round-trips through its dict (and JSON) exactly, and a stored
dict with a key missing or of the wrong type is a DocumentError naming the document and
the key."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from nanoasm.bodies import Body
from nanoasm.errors import InputError
from nanoasm.executor.documents import (CHANNELS, CHECKPOINT_FORMAT, PLAN, PUSH, TOPICS, TYPES, CheckpointDoc,
                                        DacDoc, DocumentError, DriftDoc, EventDoc, FullScanDoc, PushDoc,
                                        ResultDoc, ScanLineDoc, StopDoc, as_dict, document_from_dict)
from nanoasm.planner import Operation, Plan
from nanoasm.planner.plan import Assignment, Expect, Unfilled
from nanoasm.world.environment import EnvObject

OP = Operation(7, "o3", "s1", ((10.0, 20.0), (30.5, 20.25)), Expect((40.0, 20.0), None))
ROD_OP = Operation(8, "r1", None, ((0.0, 0.0), (1.0, 1.0), (2.0, 0.5)), Expect((5.0, 6.0), 12.5))


def docs():
    """One of every document, with awkward floats (thirds, tiny, negative zero)."""
    rod = EnvObject("r1", "rod", (1 / 3, 2e-9), 10.0, -45.125, 80.0, 0.75, True)
    return [
        EventDoc(12.5, "warn", "push of o3 slipped"),
        StopDoc("failed", "RuntimeError: boom"),
        PushDoc(op=OP, verdict="pushing", t=101.0 / 3, offset=(1250.1, -0.0), before=(10.0, 20.0),
                peak_force=3.25, belief=EnvObject("o3", "particle", (39.5, 20.1), 20.0, confidence=0.9)),
        PushDoc(op=ROD_OP, verdict="slipped", t=5.0, offset=(0.0, 0.0), before=(1.0, 2.0), peak_force=None,
                belief=rod, pivot={"offset": -0.021, "std": 0.004, "pushes": 3.0, "angle": 187.5}),
        PushDoc(op=OP, verdict="stuck", t=5.0, offset=(0.0, 0.0), before=(1.0, 2.0), peak_force=0.0,
                belief=Body("o3", "particle", (1.0, 2.0), 20.0)),
        DriftDoc(t=7.0, offset=(0.1, 0.2), cov=((4.0, 0.5), (0.5, 9.0)), velocity=(1e-3, -2e-3)),
        DriftDoc(t=7.0, offset=(0.0, 0.0), cov=None, velocity=None),
        ScanLineDoc(t=9.5, a=(1.0, 2.0), b=(3.0, 4.0), heights=np.array([0.0, 1 / 3, 2.5]), offset=(5.0, 6.0)),
        DacDoc(t=(0.0, 0.1), x=(1.0, 2.0), y=(3.0, 4.0), z=(5.0, 6.0), kind=(0, 2), s_n=(0.1, 0.2),
               s_l=(0.3, -0.4), n=100, every=50),
        FullScanDoc(t=300.0, height=np.arange(6.0).reshape(2, 3) / 7, pixel_size=9.765625, origin=(-1.5, 2.0)),
        CheckpointDoc({"format": CHECKPOINT_FORMAT, "t": 55.5, "done": 3, "belief": {"objects": []}},
                      (55.0, 1.5, -2.25)),
        CheckpointDoc({"format": CHECKPOINT_FORMAT, "t": 1}, None),
        ResultDoc(assignment=(Assignment("s1", "o3"),), unfilled=(Unfilled("s2", "no object fits"),),
                  pushed=("o3", "o3"), counts={"pushes": 2, "local_scans": 5, "replans": 0, "failed_pushes": 1},
                  times={"full_scan": 300.0, "push": 1 / 3}, wall={"plan": 0.125},
                  failures=(("o3", "slipped"),), epoch=0.5, origin=(250.0, 250.0)),
        ResultDoc((), (), (), {}, {}, {}, (), 0.0, (0.0, 0.0)),
    ]


def _topic(doc) -> str:
    return next(t for t, cls in TYPES.items() if isinstance(doc, cls))


@pytest.mark.parametrize("doc", docs(), ids=lambda d: type(d).__name__)
def test_every_document_round_trips_exactly(doc):
    cls = type(doc)
    assert cls.from_dict(doc.to_dict()) == doc
    if cls is not FullScanDoc:            # its heights go to a Grid, not to JSON
        stored = json.loads(json.dumps(doc.to_dict()))
        assert cls.from_dict(stored) == doc
        assert document_from_dict(_topic(doc), stored) == doc
        assert json.dumps(cls.from_dict(stored).to_dict()) == json.dumps(doc.to_dict())
    assert as_dict(doc) == doc.to_dict()


def test_the_dicts_are_the_logged_ones():
    """The keys and values the run log has always kept (its format does not change)."""
    push = docs()[2].to_dict()
    assert list(push) == ["op", "verdict", "t", "offset", "before", "peak_force", "belief"]
    assert push["op"] == OP.to_dict() and push["offset"] == [1250.1, -0.0] and push["belief"]["confidence"] == 0.9
    assert docs()[7].to_dict() == {"t": 9.5, "a": [1.0, 2.0], "b": [3.0, 4.0], "heights": [0.0, 1 / 3, 2.5],
                                   "offset": [5.0, 6.0]}
    assert docs()[5].to_dict() == {"t": 7.0, "offset": [0.1, 0.2], "cov": [[4.0, 0.5], [0.5, 9.0]],
                                   "velocity": [1e-3, -2e-3]}
    ck = docs()[10].to_dict()
    assert list(ck)[-1] == "drift" and ck["drift"] == [55.0, 1.5, -2.25] and docs()[10].t == 55.5
    res = docs()[12].to_dict()
    assert res["failures"] == [{"object": "o3", "cause": "slipped"}] and res["origin"] == [250.0, 250.0]
    assert list(res) == ["assignment", "unfilled", "pushed", "counts", "times", "wall", "failures", "epoch",
                         "origin"]
    assert as_dict({"t": 1}) == {"t": 1}
    rod_push = docs()[3].to_dict()                  # a rod's push adds its pivot offset estimate
    assert list(rod_push)[-1] == "pivot" and rod_push["pivot"]["offset"] == -0.021


def test_nan_heights_are_kept():
    doc = ScanLineDoc(t=1.0, a=(0, 0), b=(1, 0), heights=[1.0, math.nan], offset=(0, 0))
    back = ScanLineDoc.from_dict(json.loads(json.dumps(doc.to_dict())))
    assert back.heights[0] == 1.0 and math.isnan(back.heights[1])


def _broken(doc, key, value):
    d = json.loads(json.dumps(doc.to_dict())) if not isinstance(doc, FullScanDoc) else doc.to_dict()
    if value is _MISSING:
        del d[key]
    else:
        d[key] = value
    return d


_MISSING = object()


@pytest.mark.parametrize("doc", docs(), ids=lambda d: type(d).__name__)
def test_a_missing_key_or_a_wrong_type_is_named(doc):
    cls = type(doc)
    kind = _topic(doc)
    for key in doc.to_dict():
        if cls is CheckpointDoc and key not in ("format", "t", "drift"):
            continue                      # the state's inner keys are the executor's
        if cls is PushDoc and key == "pivot":       # only rods' pushes have one
            assert cls.from_dict(_broken(doc, key, _MISSING)).pivot is None
        else:
            with pytest.raises(DocumentError) as err:
                cls.from_dict(_broken(doc, key, _MISSING))
            assert f"{kind} document" in str(err.value) and key in str(err.value), str(err.value)
            assert isinstance(err.value, ValueError) and isinstance(err.value, InputError)
        with pytest.raises(DocumentError) as err:
            cls.from_dict(_broken(doc, key, "x" if key != "text" and key != "level" and key != "state"
                                  and key != "reason" and key != "verdict" else 5))
        assert f"{kind} document" in str(err.value) and key in str(err.value), str(err.value)


def test_nested_errors_name_the_key_inside():
    d = docs()[2].to_dict()
    d["belief"] = {**d["belief"], "diameter": -1.0}
    with pytest.raises(DocumentError, match=r"push document: belief.diameter: must be positive"):
        PushDoc.from_dict(d)
    d = docs()[2].to_dict()
    d["op"] = {**d["op"], "tip_path": [[0, 0]]}
    with pytest.raises(DocumentError, match=r"push document: op.tip_path: must have at least 2"):
        PushDoc.from_dict(d)
    d = docs()[12].to_dict()
    d["failures"] = [{"object": "o3"}]
    with pytest.raises(DocumentError, match=r"result document: failures\[1\].cause: missing"):
        ResultDoc.from_dict(d)
    d = docs()[12].to_dict()
    d["counts"] = {"pushes": 1.5}
    with pytest.raises(DocumentError, match=r"result document: counts.pushes: must be an integer"):
        ResultDoc.from_dict(d)
    d = docs()[5].to_dict()
    d["cov"] = [[1.0, 0.0], [0.0]]
    with pytest.raises(DocumentError, match=r"drift document: cov\[1\]: must be an array of 2 numbers"):
        DriftDoc.from_dict(d)
    with pytest.raises(DocumentError, match=r"checkpoint document: format: must be 'nanoasm.checkpoint/1'"):
        CheckpointDoc.from_dict({"format": "nanoasm.checkpoint/0", "t": 1.0, "drift": None})
    with pytest.raises(DocumentError, match=r"stop document: must be a table, got an array|stop document: must be a table"):
        StopDoc.from_dict([1, 2])
    with pytest.raises(DocumentError, match=r"dac document: kind: must hold integers"):
        DacDoc.from_dict({**docs()[8].to_dict(), "kind": [0.5, 1]})
    with pytest.raises(DocumentError, match=r"full_scan document: height: must be a 2-D"):
        FullScanDoc.from_dict({**docs()[9].to_dict(), "height": [1.0, 2.0]})


def test_environment_and_plan_documents_and_topics():
    plan = Plan("bowtie", (Assignment("s1", "o3"),), (OP,), ())
    assert document_from_dict(PLAN, json.loads(json.dumps(plan.to_dict()))) == plan
    with pytest.raises(DocumentError, match=r"plan document: format"):
        document_from_dict(PLAN, {"operations": []})
    with pytest.raises(DocumentError, match="unknown topic"):
        document_from_dict("pushes", {})
    assert set(CHANNELS) <= set(TOPICS) and CHANNELS[PUSH] == "/push" and len(set(TOPICS)) == len(TOPICS)


def test_a_result_tells_what_the_drift_measurements_took_and_older_results_still_read():
    doc = ResultDoc((), (), (), {}, {}, {}, (), 0.0, (0.0, 0.0),
                    purposes={"reference": 12.5, "relocalise": 0.0, "bootstrap": 4.0})
    back = ResultDoc.from_dict(json.loads(json.dumps(doc.to_dict())))
    assert back == doc and back.purposes["reference"] == 12.5
    older = {k: v for k, v in doc.to_dict().items() if k != "purposes"}
    assert ResultDoc.from_dict(older).purposes is None
    with pytest.raises(DocumentError, match="purposes.reference"):
        ResultDoc.from_dict({**doc.to_dict(), "purposes": {"reference": "soon"}})

"""Run logs: a dry-run written to MCAP through foxglove-sdk and read back, topic by topic;
cut short anywhere, killed mid-run, and streamed live over Foxglove's WebSocket protocol."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from runlogkit import kill_when, logged_dry_run, particle_bowtie

from nanoasm.cad.layout import layout_from_dict
from nanoasm.dryrun import TRUTH_TOPICS
from nanoasm.errors import InputError
from nanoasm.executor.documents import (CHANNELS, CHECKPOINT, DAC, DRIFT, ENVIRONMENT, EVENT, PLAN, PUSH, RESULT,
                                        SCAN_LINE, STOP, CheckpointDoc, DriftDoc, EventDoc, PushDoc, StopDoc,
                                        document_from_dict)
from nanoasm.executor.logread import last_checkpoint, read_log
from nanoasm.executor.runlog import TOPICS, RunLog, open_run_log
from nanoasm.review import review

GOLDEN = Path(__file__).parent / "golden" / "runlog_channels.json"


@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    path = tmp_path_factory.mktemp("runlog") / "run.mcap"
    out, rec = logged_dry_run(path)
    return path, out, rec, read_log(path)


def test_every_topic_is_written_and_read_back(logged):
    path, out, rec, log = logged
    assert log.complete and log.problem is None and log.read_bytes == log.size == path.stat().st_size
    topics = TOPICS + TRUTH_TOPICS
    assert {t for t, _, _ in topics} == set(log.channels), "every topic has a channel in a dry-run log"
    for topic, schema, _ in topics:
        msgs = log.topic(topic)
        assert msgs, f"nothing on {topic}"
        assert all(m.schema == schema for m in msgs)
    # the JSON topics hold exactly what the procedure emitted
    for engine_topic in (ENVIRONMENT, PLAN, PUSH, DRIFT, CHECKPOINT, RESULT, STOP):
        topic = CHANNELS[engine_topic]
        assert [m.data for m in log.topic(topic)] == rec.topic(engine_topic), topic
        # and read back typed, each is the document sent
        assert [d.to_dict() for _, d in log.documents(engine_topic)] == rec.topic(engine_topic), topic
    # sampled topics to 1e-6
    for engine_topic, key in ((SCAN_LINE, "heights"), (DAC, "s_n")):
        logged_docs, sent = [m.data for m in log.topic(CHANNELS[engine_topic])], rec.topic(engine_topic)
        assert len(logged_docs) == len(sent) and [set(d) for d in logged_docs] == [set(d) for d in sent]
        for a, b in zip(logged_docs, sent):
            assert a[key] == pytest.approx(b[key], abs=1e-6) and a["t"] == pytest.approx(b["t"], abs=1e-6)
    # Foxglove messages decode to what was logged
    texts = [m.data.message for m in log.topic("/events")]
    assert [d["text"] for d in rec.topic(EVENT)] == texts[:-1] and texts[-1] == "run done: completed"
    grid = log.last("/scan").data
    rows = len(grid.data) // grid.row_stride
    assert grid.column_count * grid.cell_size.x == pytest.approx(5000, rel=0.01) and rows == grid.column_count
    assert [f.name for f in grid.fields] == ["height"]
    heights = np.frombuffer(grid.data, "<f4")
    assert np.isfinite(heights).all() and heights.max() > 40          # particles stand out
    slots = {e.id for e in log.last("/layout").data.entities}
    assert {f"slot:{t.id}" for t in particle_bowtie()[1].targets} <= slots
    objects = log.topic("/objects")[0].data.entities
    assert len(objects) == len(out.summary.env.objects)
    # a push document (and tip path) per operation; the count is of strokes: a long push goes in legs
    assert len(log.topic("/tip_paths")) == len(log.topic("/push")) <= out.report.counts.pushes
    assert all(len(m.data.entities[0].lines[0].points) >= 2 for m in log.topic("/tip_paths"))
    # times are the instrument clock, in order where the engine sent them
    events = [m.t for m in log.topic("/events")]
    assert events == sorted(events) and events[-1] <= out.report.instrument_time.total + 1e-6
    # drift estimates come with their covariance; DAC chunks downsampled by 50
    d = log.last("/drift").data
    assert np.asarray(d["cov"]).shape == (2, 2) and len(d["offset"]) == 2
    dac = log.topic("/dac")[0].data
    assert len(dac["t"]) == len(dac["x"]) == -(-dac["n"] // dac["every"]) and dac["every"] == 50


def test_truth_is_the_harness_own_and_matches_the_report(logged):
    _, out, _, log = logged
    truth = {m.data["phase"]: m.data for m in log.topic("/sim/truth")}
    assert [o["id"] for o in truth["final"]["objects"]] == [b.id for b in out.report.final_objects]
    assert truth["final"]["objects"] == [b.to_dict() for b in out.report.final_objects]
    assert truth["initial"]["objects"] == [b.to_dict() for b in out.report.initial_objects]


def test_attachments_and_metadata(logged):
    _, out, _, log = logged
    scene, layout = particle_bowtie()
    assert set(log.attachments) == {"layout.json", "scene.json", "plan.json", "instrument.json", "full_scan.npz"}
    assert layout_from_dict(log.attachment_json("layout.json")) == layout
    assert log.attachment_json("scene.json") == json.loads(scene.dumps_json())
    assert log.attachment_json("plan.json") == log.topic("/plan")[0].data
    assert log.attachment_json("instrument.json")["sample_rate"] > 0
    meta = log.metadata["nanoasm"]
    assert meta["format"] == "nanoasm.runlog/1" and meta["seed"] == "3" and meta["strategy"] == "full"
    assert {"nanoasm", "python", "numpy", "foxglove-sdk", "mcap"} <= set(meta)
    assert log.metadata["dry-run"] == {"seed": "3"}


def test_the_last_checkpoint_comes_back_losslessly(logged):
    path, _, rec, _ = logged
    cp = last_checkpoint(path)
    assert isinstance(cp, CheckpointDoc) and cp.to_dict() == rec.topic(CHECKPOINT)[-1]
    assert {"remaining", "belief", "counts", "times", "pushed", "drift"} <= set(cp.to_dict())
    assert cp.ledger().counts == cp.state["counts"] and cp.belief().objects


def test_the_channel_list_is_stable(logged):
    """Golden: topics, encodings and schema names (Foxglove panels and review depend on them)."""
    from mcap.records import Channel, Schema
    from mcap.stream_reader import StreamReader

    path = logged[0]
    schemas, rows = {}, {}
    with open(path, "rb") as fh:
        for r in StreamReader(fh).records:
            if isinstance(r, Schema):
                schemas[r.id] = r
            elif isinstance(r, Channel):
                rows[r.topic] = [r.topic, r.message_encoding, schemas[r.schema_id].name,
                                 schemas[r.schema_id].encoding]
    assert sorted(rows.values()) == json.loads(GOLDEN.read_text())


def test_the_readme_lists_every_topic_with_its_schema():
    readme = (Path(__file__).parent.parent / "docs" / "logs.md").read_text()   # the topic table lives there
    rows = {}
    for line in readme.splitlines():
        if line.startswith("| `/"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[0].strip("`")] = cells[1]
    assert rows == {t: s for t, s, _ in TOPICS + TRUTH_TOPICS}


def test_a_log_cut_anywhere_is_read_and_reviewed_as_far_as_it_goes(logged, tmp_path):
    path, _, _, full = logged
    data = path.read_bytes()
    rng = random.Random(6)
    cuts = sorted({1, 7, 8, 9, 100, len(data) - 1, len(data) - 8, *(rng.randrange(1, len(data)) for _ in range(40))})
    cut_file = tmp_path / "cut.mcap"
    before = -1
    for cut in cuts:
        cut_file.write_bytes(data[:cut])
        log = read_log(cut_file)
        assert not log.complete and log.problem, cut
        assert log.read_bytes <= cut
        n = len(log.messages)
        assert n >= before                     # a longer prefix never holds less
        before = n
        assert [(m.topic, m.t) for m in log.messages] == [(m.topic, m.t) for m in full.messages[:n]]
        rev = review(cut_file)
        assert not rev.complete and rev.pushes <= 14
    assert before > 0


@pytest.mark.parametrize("content, message", [(None, "no such file"), (b"", "empty"),
                                              (b"hello, this is not a log\n", "not an MCAP")])
def test_an_empty_or_foreign_file_is_refused(tmp_path, content, message):
    path = tmp_path / "bad.mcap"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=message):
        read_log(path)


def test_bad_log_options_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="must end in .mcap"):
        open_run_log(tmp_path / "run.json")
    with pytest.raises(InputError, match="does not exist"):
        open_run_log(tmp_path / "nowhere" / "run.mcap")
    with pytest.raises(InputError, match="--live-port"):
        open_run_log(None, live_port=70000)
    first = open_run_log(None, live_port=0)
    try:
        with pytest.raises(InputError, match="cannot serve"):
            open_run_log(tmp_path / "run.mcap", live_port=first.port)
    finally:
        first.close()


def test_a_failed_run_closes_its_log_without_waiting_for_the_truth(tmp_path):
    log = RunLog(tmp_path / "r.mcap", truth=True)
    log(EVENT, EventDoc(1.0, "info", "started"))
    log(STOP, StopDoc("failed", "RuntimeError: boom"))
    log.close()
    assert log._closed
    read = read_log(tmp_path / "r.mcap")
    assert read.complete and read.documents(STOP) == [(STOP, StopDoc("failed", "RuntimeError: boom"))]
    assert [m.data.message for m in read.topic("/events")] == ["started", "run failed: RuntimeError: boom"]
    log.close()                                 # idempotent
    log(EVENT, EventDoc(2.0, "info", "ignored after close"))


def test_a_killed_dry_run_leaves_a_readable_prefix(tmp_path):
    """SIGKILL the CLI mid-run: the log holds everything up to the last flush (a push)."""
    _, layout = particle_bowtie()
    layout_file = tmp_path / "particles.toml"
    layout.save(layout_file)
    from nanoasm.examples import path as example

    out = tmp_path / "killed.mcap"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.Popen([sys.executable, "-m", "nanoasm.cli", "dry-run", str(example("bowtie_scene.toml")),
                             str(layout_file), "--seed", "3", "--log", str(out)],
                            cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    kill_when(proc, lambda: out.exists() and bool(read_log(out, topics={"/push"}).topic("/push")), 120.0)
    log = read_log(out)
    assert not log.complete
    assert log.topic("/push") and log.topic("/environment") and log.attachments.get("layout.json")
    assert not log.topic("/stop")
    rev = review(out)
    assert not rev.complete and rev.pushes >= 1 and rev.layout == layout


def test_the_live_server_serves_a_client_on_localhost():
    """A Foxglove WebSocket client on 127.0.0.1 sees every channel advertised and gets a message."""
    from websockets.sync.client import connect

    log = RunLog(None, live_port=0)
    try:
        assert log.writer is None and log.port > 0
        with connect(f"ws://127.0.0.1:{log.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
            info = json.loads(ws.recv(timeout=10))
            assert info["op"] == "serverInfo" and info["name"] == "nanoasm"
            adv = json.loads(ws.recv(timeout=10))
            assert adv["op"] == "advertise"
            channels = {c["topic"]: c for c in adv["channels"]}
            assert set(channels) == {t for t, _, _ in TOPICS}
            assert channels["/events"]["schemaName"] == "foxglove.Log"
            assert channels["/drift"]["encoding"] == "json"
            subs = {"/events": 1, "/drift": 2}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": channels[t]["id"]} for t, i in subs.items()]}))
            got: dict[int, bytes] = {}
            deadline = time.monotonic() + 10
            while len(got) < 2 and time.monotonic() < deadline:
                # the server may not have registered the subscription yet: log until it arrives
                log(EVENT, EventDoc(1.5, "warn", "hello live"))
                log(DRIFT, DriftDoc(1.5, (1.0, 2.0), ((1.0, 0.0), (0.0, 1.0)), None))
                try:
                    frame = ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                if isinstance(frame, bytes) and frame[0] == 1:        # opcode 1: message data
                    sub = int.from_bytes(frame[1:5], "little")
                    assert int.from_bytes(frame[5:13], "little") == 1_500_000_000
                    got[sub] = frame[13:]
            assert json.loads(got[2])["offset"] == [1.0, 2.0]
            assert b"hello live" in got[1]             # a foxglove.Log protobuf
    finally:
        log.close()


def test_a_document_and_its_dict_are_logged_alike(logged, tmp_path):
    """While producers still emit dicts, the run log takes both: the same records."""
    _, _, rec, _ = logged
    sent = rec.topic(PUSH)[0]
    for name, doc in (("typed", PushDoc.from_dict(sent)), ("dict", sent)):
        log = RunLog(tmp_path / f"{name}.mcap")
        log(PUSH, doc)
        log.close()
    typed, plain = read_log(tmp_path / "typed.mcap"), read_log(tmp_path / "dict.mcap")
    assert [m.data for m in typed.topic("/push")] == [m.data for m in plain.topic("/push")] == [sent]
    for topic in ("/tip_paths", "/belief"):
        wire = [[m.data.SerializeToString() for m in log.topic(topic)] for log in (typed, plain)]
        assert wire[0] == wire[1] and wire[0], topic
    assert document_from_dict(PUSH, sent).to_dict() == sent


def test_the_full_scan_attachment_keeps_the_scan_exactly_and_refuses_other_bytes(logged):
    from nanoasm.executor.scan_attachment import full_scan_bytes, full_scan_image

    _, _, _, log = logged
    image = full_scan_image(log.attachments["full_scan.npz"])
    assert image.height.ndim == 2 and image.pixel_size > 0 and np.isfinite(image.height).all()
    doc = {"height": np.arange(12.0).reshape(3, 4) / 3, "pixel_size": 2.5, "origin": (-1.0, 0.5)}
    back = full_scan_image(full_scan_bytes(doc))
    assert np.array_equal(back.height, doc["height"]) and back.pixel_size == 2.5 and back.origin == (-1.0, 0.5)
    for bad in (b"", b"PK\x03\x04 not a zip", full_scan_bytes({**doc, "height": np.ones(3)})):
        with pytest.raises(ValueError, match="not a full-scan attachment"):
            full_scan_image(bad)


def test_the_full_scan_attachment_is_deflated_only_where_that_pays():
    import io
    import zipfile

    from nanoasm.executor.scan_attachment import full_scan_bytes, full_scan_image

    rng = np.random.default_rng(5)
    flat = np.zeros((300, 400))
    flat[100:140, 200:230] = 40.0                                            # a terrace and a particle
    noisy = flat + rng.normal(0.0, 0.3, flat.shape)                          # noise in every bit
    for height, deflated in ((flat, True), (noisy, False)):
        data = full_scan_bytes({"height": height, "pixel_size": 10.0, "origin": (0.0, 0.0)})
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            kinds = {i.filename: i.compress_type for i in zf.infolist()}
        assert (kinds["height.npy"] == zipfile.ZIP_DEFLATED) is deflated
        assert len(data) < height.nbytes / 10 if deflated else len(data) > height.nbytes
        assert np.array_equal(full_scan_image(data).height, height)


def test_a_documents_floats_are_rounded_as_one_at_a_time():
    """``_rounded`` (a list's floats rounded without a call each) gives what rounding
    every float one call at a time gives, numpy floats, ints, bools and strings among
    them, at any depth."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from nanoasm.executor.runlog import _DIGITS, _rounded

    def one_at_a_time(doc):
        if isinstance(doc, float):
            return round(doc, _DIGITS)
        if isinstance(doc, dict):
            return {k: one_at_a_time(v) for k, v in doc.items()}
        if isinstance(doc, (list, tuple)):
            return [one_at_a_time(v) for v in doc]
        return doc

    leaf = st.one_of(st.floats(allow_nan=False), st.floats(-1e6, 1e6).map(np.float64), st.integers(), st.booleans(),
                     st.text(max_size=3), st.none())
    docs = st.recursive(leaf, lambda inner: st.one_of(st.lists(inner, max_size=6), st.tuples(inner, inner),
                                                      st.dictionaries(st.text(max_size=3), inner, max_size=4)))

    @settings(max_examples=300, deadline=None)
    @given(docs)
    def check(doc):
        got, want = _rounded(doc), one_at_a_time(doc)
        assert json.dumps(got) == json.dumps(want) and type(got) is type(want)

    check()

"""Run logs: every dry-run and run as one MCAP file, written through foxglove-sdk.

A :class:`RunLog` is a :class:`~nanoasm.executor.engine.RunEngine` subscriber. It turns
the engine's topics into MCAP channels, with Foxglove's well-known protobuf schemas where
one fits (``foxglove.Log``, ``foxglove.SceneUpdate``, ``foxglove.Grid``) and JSON with a
JSON schema elsewhere; :data:`TOPICS` lists them. The same channels stream live over
Foxglove's WebSocket protocol when a live port is given (bound to 127.0.0.1).

Log times are the instrument's clock in nanoseconds. The file is written in chunks and
flushed after every push, checkpoint, plan and scan, so a process killed at any moment
leaves a readable prefix (:func:`nanoasm.executor.logread.read_log` reads it). Positions
are in nm in the layout frame (``frame_id`` ``"layout"``) unless a topic says
``scanner``; Foxglove's 3-D panel shows 1 nm as 1 m.

Only what the executor knows goes into the log; the harness may add channels of its own
(:meth:`RunLog.add_channel`, :meth:`RunLog.write`). JSON is :mod:`.json_parts`'s."""

from __future__ import annotations

import json
import math
import platform
import sys
import time
from dataclasses import asdict, is_dataclass
from typing import Any

import numpy as np

from .documents import (CHANNELS, CHECKPOINT, DAC, ENVIRONMENT, EVENT, FAILED_VERDICTS, FULL_SCAN, PLAN, PUSH,
                        RESULT, SCAN_LINE, STOP, Document, as_dict)
from . import json_parts
from .scan_attachment import FULL_SCAN_ATTACHMENT, full_scan_bytes
from .foxglove_scenes import (COLOURS, believed, bodies_scene, grid, layout_scene, log_line, nanoseconds,
                              paths_scene, scan_line_scene, timestamp)
from .scan_surface import DESCRIPTION as SURFACE_DESCRIPTION, SURFACE_TOPIC, SurfaceView

#: The run log's format name (MCAP profile and metadata).
FORMAT = "nanoasm.runlog/1"
#: Every DAC chunk is logged at every ``DAC_EVERY``-th sample.
DAC_EVERY = 50

# (topic, schema name, what it holds); JSON channels have schema names nanoasm.*
TOPICS: tuple[tuple[str, str, str], ...] = (
    ("/events", "foxglove.Log", "the run's log lines (info, warning, error)"),
    ("/layout", "foxglove.SceneUpdate", "slots, keep-outs and the working area (in the scan's frame once registered)"),
    ("/scan", "foxglove.Grid", "the full scan: heights (nm, float32) on the layout frame"),
    (SURFACE_TOPIC, "foxglove.SceneUpdate", SURFACE_DESCRIPTION),
    ("/objects", "foxglove.SceneUpdate", "objects identified in the full scan"),
    ("/plan/paths", "foxglove.SceneUpdate", "tip paths of the plan, again at every replan"),
    ("/belief", "foxglove.SceneUpdate", "the executor's belief: every object's believed pose, after each push"),
    ("/tip_paths", "foxglove.SceneUpdate", "the tip path of every push as executed, coloured by verdict"),
    ("/local_scan/lines", "foxglove.SceneUpdate", "the latest local-scan line, layout frame"),
    ("/environment", "nanoasm.Environment", "identified objects and obstacles (nanoasm.env/1)"),
    ("/plan", "nanoasm.Plan", "the first plan and every replan (nanoasm.plan/1)"),
    ("/push", "nanoasm.Push", "each push: operation, verdict, peak force, start pose, belief after"),
    ("/drift", "nanoasm.DriftEstimate", "drift estimate after each filter update, with covariance"),
    ("/local_scan", "nanoasm.ScanLine", "each local-scan line: end points (scanner frame) and heights, "
     "to 1e-6"),
    ("/dac", "nanoasm.DacChunk", f"each DAC chunk of a push, every {DAC_EVERY}th sample: time, XYZ nm "
     "(scanner frame), sample kind, photodiode signals S_n, S_l; to 1e-6"),
    ("/checkpoint", "nanoasm.Checkpoint", "the procedure's state after each push, losslessly (for resume)"),
    ("/result", "nanoasm.Result", "what the run did: assignment, unfilled slots, counts, times, failures"),
    ("/stop", "nanoasm.Stop", "how the run ended: state and reason"),
)

#: Bulky sampled topics whose numbers are logged to ``_DIGITS`` decimals (µs, pm, µV):
#: full precision doubles them (bowtie dry-run: /local_scan 722 -> 356 kB, /dac 120 -> 75 kB
#: before compression) for digits below the noise.
_ROUNDED = {SCAN_LINE, DAC}
_DIGITS = 6
#: Topics after which the file is flushed (a SIGKILL then loses nothing before them).
_FLUSH_AFTER = {ENVIRONMENT, PLAN, PUSH, CHECKPOINT, RESULT, STOP, FULL_SCAN}

def _plain(v: Any) -> Any:
    """``json.dumps`` default: numpy values and arrays, dataclasses, sets, tuples as lists."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (set, frozenset)):
        return sorted(v)
    if is_dataclass(v) and not isinstance(v, type):
        return asdict(v)
    raise TypeError(f"cannot log {type(v).__name__} as JSON")


def _rounded(doc: Any) -> Any:
    """``doc`` with every float rounded to ``_DIGITS`` decimals (a list's without a call each)."""
    if isinstance(doc, float):
        return round(doc, _DIGITS)
    if isinstance(doc, dict):
        return {k: _rounded(v) for k, v in doc.items()}
    if isinstance(doc, (list, tuple)):
        return [round(v, _DIGITS) if isinstance(v, float) else _rounded(v) for v in doc]
    return doc


def to_json(doc: Any) -> bytes:
    """The JSON bytes of a document, as logged (NaN kept, so nothing is lost)."""
    return json_parts.dumps(doc, _plain).encode("utf-8")     # json.dumps's bytes, parts kept encoded once


def _json_schema(name: str, description: str, required: tuple[str, ...] = ()) -> dict:
    return {"title": name, "description": description, "type": "object",
            "required": list(required)}


#: JSON schemas of the custom channels (loose: the documents are the engine's own).
_SCHEMAS = {
    "nanoasm.Environment": _json_schema("nanoasm.Environment", "nanoasm.env/1", ("objects",)),
    "nanoasm.Plan": _json_schema("nanoasm.Plan", "nanoasm.plan/1", ("operations",)),
    "nanoasm.Push": _json_schema("nanoasm.Push", "one push", ("op", "verdict", "t")),
    "nanoasm.DriftEstimate": _json_schema("nanoasm.DriftEstimate",
                                          "drift offset (nm) and covariance (nm^2) at t", ("t", "offset")),
    "nanoasm.ScanLine": _json_schema("nanoasm.ScanLine", "a local-scan line, scanner frame",
                                     ("a", "b", "heights")),
    "nanoasm.DacChunk": _json_schema("nanoasm.DacChunk", "a DAC chunk, downsampled", ("t", "x", "y", "z")),
    "nanoasm.Checkpoint": _json_schema("nanoasm.Checkpoint", "procedure state", ("remaining", "belief")),
    "nanoasm.Result": _json_schema("nanoasm.Result", "what the run did", ("counts",)),
    "nanoasm.Stop": _json_schema("nanoasm.Stop", "how the run ended", ("state", "reason")),
}


def versions() -> dict[str, str]:
    """Versions of what wrote the log."""
    from importlib.metadata import PackageNotFoundError, version

    from nanoasm import __version__

    out = {"nanoasm": __version__, "python": platform.python_version(), "numpy": np.__version__}
    for dist in ("foxglove-sdk", "mcap"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:  # pragma: no cover - both are dependencies
            pass
    return out


class RunLog:
    """Engine subscriber writing the run to ``path`` (MCAP) and/or streaming it live.

    Parameters
    ----------
    path : str or path, optional
        The MCAP file (overwritten). None: no file (live view only).
    live_port : int, optional
        Stream the same channels over Foxglove's WebSocket protocol on 127.0.0.1 at this
        port (0: any free port; :attr:`port` tells which).
    layout : Layout, optional
        Attached as ``layout.json`` and drawn on ``/layout``.
    metadata : dict, optional
        Written as the MCAP metadata record ``nanoasm`` (strings), besides the versions.
    attachments : dict, optional
        ``name -> (media type, bytes)``, attached at the start (e.g. the instrument file).
    truth : bool
        Held open for its harness: after a completed run the engine's ``close()`` only
        flushes; the harness adds its own records (:meth:`write`, a dry-run's truth) and
        calls :meth:`finish`. A run that did not complete closes as usual.
    """

    def __init__(self, path=None, *, live_port: int | None = None, layout=None,
                 metadata: dict[str, Any] | None = None,
                 attachments: dict[str, tuple[str, bytes]] | None = None, truth: bool = False):
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self._fg = foxglove
        self.context = foxglove.Context()
        self.path = None if path is None else str(path)
        self.writer = None
        self.server = None
        self._closed = False
        self._await_truth = truth
        self._hold = self.stopped = False       # stopped: the run's /stop recorded
        self._t = 0.0                 # latest instrument time seen (s)
        self._pushes, self._drawn = 0, {}      # the memo of the checkpoints' /belief (bodies_scene)
        self._plan_attached = False
        self._layout = layout
        self._handlers = {EVENT: self._on_event, STOP: self._on_stop, FULL_SCAN: self._on_full_scan,
                          ENVIRONMENT: self._on_environment, PLAN: self._on_plan, PUSH: self._on_push,
                          CHECKPOINT: self._on_checkpoint, SCAN_LINE: self._on_scan_line}
        self._surface = SurfaceView(self._log, self._stamp)      # the full scan in 3-D (.scan_surface)
        if live_port is not None:
            self.server = foxglove.start_server(name="nanoasm", host="127.0.0.1", port=live_port,
                                                context=self.context)
        if self.path is not None:
            options = MCAPWriteOptions(compression=MCAPCompression.Zstd, profile=FORMAT,   # level 2: 3's size,
                                       compression_threads=0, compression_level=2)      # a quarter less CPU
            try:
                self.writer = foxglove.open_mcap(self.path, allow_overwrite=True, context=self.context,
                                                 writer_options=options)
            except BaseException:
                if self.server is not None:
                    self.server.stop()
                raise
        self.channels = self._open_channels()
        meta = {"format": FORMAT, **versions(), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        meta.update({k: str(v) for k, v in (metadata or {}).items() if v is not None})
        self.metadata("nanoasm", meta)
        for name, (media, data) in (attachments or {}).items():
            self.attach(name, data, media)
        if layout is not None:
            self.attach("layout.json", layout.dumps_json().encode("utf-8"), "application/json")
            self._log("/layout", layout_scene(layout), 0.0)
        self.flush()

    @property
    def port(self) -> int | None:
        """Port of the live server, if any."""
        return None if self.server is None else self.server.port

    def _open_channels(self) -> dict[str, Any]:
        return {topic: self._channel(topic, schema, _SCHEMAS.get(schema)) for topic, schema, _ in TOPICS}

    def _channel(self, topic: str, schema: str, json_schema: dict | None) -> Any:
        """A channel of a Foxglove message (``foxglove.*``), or of JSON with ``json_schema``."""
        fg, fm = self._fg, self._fg.messages

        if schema.startswith("foxglove."):     # the message's protobuf schema; _log encodes (or is given bytes)
            kind = getattr(fm, schema.split(".", 1)[1])
            return fg.Channel(topic, context=self.context, message_encoding="protobuf", schema=kind.get_schema())
        return fg.Channel(topic, context=self.context, message_encoding="json",
                          schema=fg.Schema(name=schema, encoding="jsonschema",
                                           data=json.dumps(json_schema).encode()))

    def add_channel(self, topic: str, schema: str, description: str = "", required: tuple[str, ...] = ()) -> None:
        """A channel of the harness's own beside :data:`TOPICS`: ``schema`` names a Foxglove
        message (``foxglove.SceneUpdate``) or titles a loose JSON schema with this
        description and these required keys."""
        if not self._closed and topic not in self.channels:
            self.channels[topic] = self._channel(topic, schema, _json_schema(schema, description, required))

    # -- writing ------------------------------------------------------------------------
    def _log(self, topic: str, msg: Any, t: float | None) -> None:
        if self._closed:
            return
        if t is not None and math.isfinite(t):
            self._t = max(self._t, float(t))
        ch = self.channels[topic]
        data = msg if isinstance(msg, bytes) else to_json(msg) if isinstance(msg, (dict, list)) else msg.encode()
        ch.log(data, log_time=nanoseconds(self._t if t is None else t))

    def flush(self) -> None:
        if self.writer is not None and not self._closed:
            self.writer.flush()

    def metadata(self, name: str, values: dict[str, str]) -> None:
        """An MCAP metadata record (string values)."""
        if self.writer is not None and not self._closed:
            self.writer.write_metadata(name, {k: str(v) for k, v in values.items()})

    def attach(self, name: str, data: bytes, media_type: str = "application/json") -> None:
        """An MCAP attachment, stamped with the latest instrument time."""
        if self.writer is not None and not self._closed:
            ns = nanoseconds(self._t)
            self.writer.attach(log_time=ns, create_time=ns, name=name, media_type=media_type, data=data)

    def __call__(self, topic: str, doc: Document | dict) -> None:
        """The engine's subscriber interface: the document's ``to_dict()`` is logged."""
        if self._closed:
            return
        d = as_dict(doc)
        t = d.get("t")
        self._record(topic, d, t if isinstance(t, (int, float)) else None)

    def _record(self, topic: str, d: dict, t: float | None) -> None:
        handler = self._handlers.get(topic)
        if handler is not None:
            handler(d, t)
        self._surface(topic, d, t)
        if topic in CHANNELS:
            self._log(CHANNELS[topic], _rounded(d) if topic in _ROUNDED else d, t)
        if topic in _FLUSH_AFTER:
            self.flush()

    def carry(self, inherited) -> None:
        """A resumed run's log: what it carries over from the stopped run's, at their times
        (:class:`~nanoasm.executor.resume.Inherited`), so that a resume needs it alone."""
        if inherited.full_scan is not None:
            self.attach(FULL_SCAN_ATTACHMENT, inherited.full_scan, media_type="application/x-npz")
        for topic, (t, doc) in ((ENVIRONMENT, inherited.environment), (PLAN, inherited.plan),
                                (CHECKPOINT, inherited.checkpoint)):
            self._record(topic, doc, t)

    def _on_event(self, doc: dict, t: float | None) -> None:
        self._log("/events", log_line(self._stamp(t), str(doc.get("level", "info")), str(doc.get("text", ""))), t)

    def _on_stop(self, doc: dict, t: float | None) -> None:
        self._on_event({"level": "info" if doc.get("state") == "done" else "error",
                        "text": f"run {doc.get('state')}: {doc.get('reason')}"}, t)
        self.stopped = True
        self._hold = self._await_truth and doc.get("state") == "done"

    def _on_full_scan(self, doc: dict, t: float | None) -> None:
        self._log("/scan", grid(doc, self._stamp(t)), t)
        self.attach(FULL_SCAN_ATTACHMENT, full_scan_bytes(doc), media_type="application/x-npz")

    def _on_environment(self, doc: dict, t: float | None) -> None:
        self._log("/objects", bodies_scene(doc.get("objects", ()), "obj", COLOURS["object"], self._stamp(t)), t)

    def _on_plan(self, doc: dict, t: float | None) -> None:
        if not self._plan_attached:
            self._plan_attached = True
            self.attach("plan.json", to_json(doc))
            if self._layout is not None and doc.get("registration"):    # the slots where the run has them
                self._log("/layout", layout_scene(self._layout, doc["registration"]), t)
        paths = [(f"op{op.get('id')}", op.get("tip_path") or ()) for op in doc.get("operations", ())]
        self._log("/plan/paths", paths_scene(paths, COLOURS["plan"], self._stamp(t), clear=True), t)

    def _on_push(self, doc: dict, t: float | None) -> None:
        self._pushes += 1
        op = doc.get("op", {})
        colour = COLOURS["failed" if doc.get("verdict") in FAILED_VERDICTS else "ok"]
        self._log("/tip_paths", paths_scene([(f"push{self._pushes}", op.get("tip_path") or ())], colour,
                                            self._stamp(t)), t)
        belief = doc.get("belief")
        if isinstance(belief, dict):
            self._log("/belief", bodies_scene([belief], "obj", COLOURS["belief"], self._stamp(t)), t)

    def _on_checkpoint(self, doc: dict, t: float | None) -> None:
        objs, lost = believed(doc)
        self._log("/belief", bodies_scene(objs, "obj", COLOURS["belief"], self._stamp(t), lost, memo=self._drawn), t)

    def _on_scan_line(self, doc: dict, t: float | None) -> None:
        scene = scan_line_scene(doc, self._stamp(t))
        if scene is not None:
            self._log("/local_scan/lines", scene, t)

    def write(self, topic: str, msg: Any, t: float | None) -> None:
        """A message on a channel (a dict or list as JSON, or a Foxglove message) at
        instrument time ``t``, s (None: the latest seen)."""
        self._log(topic, msg, t)

    def write_bodies(self, topic: str, bodies, t: float | None, *, prefix: str, colour) -> None:
        """Bodies (``Body.to_dict()`` documents) drawn on a ``foxglove.SceneUpdate`` channel,
        each as entity ``prefix:id`` in ``colour`` (r, g, b, a)."""
        self._log(topic, bodies_scene(bodies, prefix, colour, self._stamp(t)), t)

    def finish(self) -> None:
        """Close the log, also after a completed run that it holds open for its harness."""
        self._hold = False
        self.close()

    def close(self) -> None:
        """Finish the file and stop the live server (idempotent). After a completed run that
        it holds open for its harness (``truth``), the first call only flushes."""
        if self._closed:
            return
        if self._hold:
            self._hold = False
            self.flush()
            return
        self._closed = True
        try:
            if self.writer is not None:
                self.writer.close()
        finally:
            if self.server is not None:
                self.server.stop()
            for ch in self.channels.values():
                ch.close()

    # -- Foxglove messages --------------------------------------------------------------
    def _stamp(self, t: float | None):
        """The Foxglove timestamp of instrument time ``t`` (None: the latest seen)."""
        return timestamp(nanoseconds(self._t if t is None else t))


def open_run_log(path=None, *, live_port: int | None = None, **kwargs) -> RunLog:
    """A :class:`RunLog` for the command line: a bad path or port is an InputError."""
    from pathlib import Path

    from nanoasm.errors import InputError

    if path is not None:
        p = Path(path)
        if p.suffix.lower() != ".mcap":
            raise InputError(str(path), None, "run log must end in .mcap")
        if not (p.parent if str(p.parent) else Path(".")).is_dir():
            raise InputError(str(path), None, f"output folder {str(p.parent)!r} does not exist")
        if p.is_dir():
            raise InputError(str(path), None, "is a directory, not a file")
    if live_port is not None and not 0 <= live_port <= 65535:
        raise InputError(None, "--live-port", f"must be a port number 0-65535, got {live_port}")
    try:
        return RunLog(path, live_port=live_port, **kwargs)
    except OSError as exc:
        raise InputError(str(path), None, f"cannot write: {exc.strerror or exc}") from None
    except RuntimeError as exc:    # foxglove: the port is taken
        if live_port is None:
            raise
        raise InputError(None, "--live-port", f"cannot serve on 127.0.0.1:{live_port}: {exc}") from None


def command_line() -> str:
    """The command line of this process, as typed (for the log's metadata)."""
    import shlex

    return " ".join(shlex.quote(a) for a in ["nanoasm", *sys.argv[1:]])

"""Helpers for the run-log tests: a small dry-run written to an MCAP log."""

from __future__ import annotations

import json
from dataclasses import replace

from nanoasm.cad.layout import load_layout
from nanoasm.dryrun import dry_run
from nanoasm.examples import path as example
from nanoasm.executor.documents import FULL_SCAN, Document, as_dict
from nanoasm.executor.runlog import RunLog, to_json
from nanoasm.executor.strategy import ExecOptions
from nanoasm.world.scene import load_scene


def particle_bowtie():
    """The bundled example without its rod slot (a dry-run of a few seconds)."""
    layout = load_layout(example("bowtie.toml"))
    layout = replace(layout, targets=tuple(t for t in layout.targets if t.kind == "particle"))
    return load_scene(example("bowtie_scene.toml")), layout


class Recorder:
    """A subscriber keeping every document as the log would store it (JSON round trip)."""

    def __init__(self):
        self.docs: list[tuple[str, object]] = []

    def __call__(self, topic: str, doc: Document | dict) -> None:
        if topic != FULL_SCAN:
            self.docs.append((topic, json.loads(to_json(as_dict(doc)))))

    def topic(self, name: str) -> list:
        return [d for t, d in self.docs if t == name]


def logged_dry_run(path, *, seed: int = 3, strategy: str = "full"):
    """A dry-run of the particle bowtie logged to ``path``; returns (outcome, recorder)."""
    scene, layout = particle_bowtie()
    rec = Recorder()
    log = RunLog(path, layout=layout, metadata={"kind": "dry-run", "seed": seed, "strategy": strategy},
                 truth=True)
    try:
        out = dry_run(scene, layout, seed=seed, options=ExecOptions(strategy=strategy), subscribers=[rec, log])
    finally:
        log.close()
    return out, rec


def kill_when(proc, ready, timeout: float = 180.0) -> None:
    """SIGKILL the subprocess ``proc`` as soon as ``ready()`` is true (polled); fails the
    test if the process ends first. The process is reaped whatever happens.

    ``ready`` may read a log the process is still creating: an :class:`InputError` (a file
    created but not yet holding its first bytes) counts as not ready yet."""
    import signal
    import time

    from nanoasm.errors import InputError

    try:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                if ready():
                    break
            except InputError:
                pass
            time.sleep(0.05)
        assert proc.poll() is None, f"the process ended before it could be killed: {proc.stderr.read()!r}"
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


#: A CLI run that SIGKILLs itself right after it kept its simulated world for the n-th
#: time (the dry-run harness keeps it after every checkpoint and, when resuming, at the
#: start): the kill lands at the same point of the run every time.
_KILLED_AFTER = """
import os, signal, sys
from nanoasm import simkeep
write, kept = simkeep.write_atomic, [0]
def keep_then_die(*args, **kwargs):
    write(*args, **kwargs)
    kept[0] += 1
    if kept[0] == int(os.environ["NANOASM_TEST_KILL_AFTER"]):
        os.kill(os.getpid(), signal.SIGKILL)
simkeep.write_atomic = keep_then_die
from nanoasm.cli import main
sys.exit(main(sys.argv[1:]))
"""


def cli_env() -> dict[str, str]:
    """The environment for a CLI subprocess: this one's, without PYTHONPATH."""
    import os

    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NANOASM_DEBUG")}


def killed_after(args: list[str], kept: int, cwd, timeout: float = 180.0) -> None:
    """Run ``nanoasm ARGS`` in a subprocess SIGKILLed right after the ``kept``-th time it
    kept its world; fails the test if it ends otherwise."""
    import signal
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", _KILLED_AFTER, *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, env={**cli_env(), "NANOASM_TEST_KILL_AFTER": str(kept)})
    assert done.returncode == -signal.SIGKILL, f"not killed (exit {done.returncode}): {done.stderr}"


def chunk_topics(path) -> list[tuple[int, int, set[str]]]:
    """Every chunk of an MCAP file: its record's first byte, the byte after it, and the
    topics of its messages (read with the mcap library, independently of the reader under
    test)."""
    from mcap.records import Channel, Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    class Counting:
        def __init__(self, fh):
            self.fh, self.count = fh, 0

        def read(self, n=-1):
            data = self.fh.read(n)
            self.count += len(data)
            return data

    out, topics = [], {}
    with open(path, "rb") as fh:
        counting = Counting(fh)
        records = StreamReader(counting, emit_chunks=True).records
        start = 8
        try:
            for rec in records:
                if isinstance(rec, Chunk):
                    inner = breakup_chunk(rec)
                    topics.update({c.id: c.topic for c in inner if isinstance(c, Channel)})
                    out.append((start, counting.count, {topics[m.channel_id] for m in inner
                                                        if isinstance(m, Message)}))
                start = counting.count
        except Exception:  # noqa: BLE001 - a log cut short ends here
            pass
    return out


def stop_when(proc, ready, signals, timeout: float = 120.0) -> str:
    """Send ``signals`` (``(seconds to wait first, signal number)``, ...) to the subprocess
    ``proc`` as soon as ``ready()`` is true (polled), then wait for its end; returns its
    stderr. Fails the test if the process ends, or is not ready in ``timeout`` s, first;
    the process is reaped whatever happens."""
    import time

    try:
        deadline = time.monotonic() + timeout
        while proc.poll() is None and time.monotonic() < deadline and not ready():
            time.sleep(0.02)
        assert proc.poll() is None and ready(), f"the process ended before it was ready: {proc.stderr.read()!r}"
        for wait, signum in signals:
            time.sleep(wait)
            proc.send_signal(signum)
        return proc.communicate(timeout=60)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()

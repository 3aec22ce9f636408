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
    test if the process ends first. The process is reaped whatever happens."""
    import signal
    import time

    try:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and proc.poll() is None:
            if ready():
                break
            time.sleep(0.05)
        assert proc.poll() is None, f"the process ended before it could be killed: {proc.stderr.read()!r}"
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()

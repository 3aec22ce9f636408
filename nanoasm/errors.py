"""Typed errors. A user's bad input becomes one line: file, key path, problem."""

from __future__ import annotations


class NanoasmError(Exception):
    """Base of every error nanoasm raises on purpose."""


class InputError(NanoasmError):
    """A file or value given by the user is wrong.

    ``str(err)`` is the single line shown to the user::

        layout.toml: target[2].diameter: must be positive, got -5
    """

    def __init__(self, source: str | None, key: str | None, problem: str):
        self.source = source
        self.key = key
        self.problem = problem
        super().__init__(self.line())

    def line(self) -> str:
        parts = [p for p in (self.source, self.key) if p]
        text = ": ".join([*parts, self.problem])
        # one line, whatever a file name or key holds
        return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class InstrumentLimitError(NanoasmError):
    """A command would leave the instrument's limits; nothing was sent."""

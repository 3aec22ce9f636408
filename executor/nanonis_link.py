"""The TCP link to a Nanonis controller, through the official ``nanonis-spm`` package.

``nanonis_spm.Nanonis`` speaks the documented protocol (a request: 32-byte command
name, int32 body size, uint16 send-response flag, two zero bytes, big-endian
arguments; a reply: the same header, the return values, then an error status, the
error text's size and the text). Three of its habits are handled here, so that a
refused command or a lost controller is one line and never a hang:

- it prints errors and returns them: :meth:`NanonisLink.call` swallows the print and
  raises :class:`NanonisError` naming the command and the controller's message;
- it sets the socket timeout to 1000 s after every reply and reads with bare
  ``recv``: it gets a socket stand-in (:class:`_Socket`) that ignores ``settimeout``,
  reads exactly the bytes asked for and raises when the controller hangs up;
- a reply that did not arrive leaves the stream out of step: the link then closes and
  only :meth:`NanonisLink.reconnect` opens it again.

``nanonis_spm`` is imported when a link opens, so the rest of nanoasm works without it.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import socket
import struct
from typing import Any

from nanoasm.errors import NanoasmError

from .nanonis_config import NanonisConfig


class NanonisError(NanoasmError):
    """The Nanonis controller is unreachable, stopped answering or refused a command."""


def load_client(module: Any = None) -> Any:
    """The ``Nanonis`` class of ``module`` (default: import ``nanonis_spm``)."""
    if module is None:
        try:
            module = importlib.import_module("nanonis_spm")
        except ImportError:
            raise NanonisError("the nanonis-spm package is not installed: pip install 'nanoasm[nanonis]' "
                               "(or nanonis-spm), or use nanoasm dry-run") from None
    return module.Nanonis


class _Socket:
    """What ``nanonis_spm.Nanonis`` calls on its connection, done safely on a real socket."""

    def __init__(self, sock: socket.socket):
        self.sock = sock

    def send(self, data: bytes) -> int:
        self.sock.sendall(data)
        return len(data)

    def recv(self, n: int) -> bytes:
        """Exactly ``n`` bytes; raises ConnectionError if the controller hung up."""
        out = bytearray()
        while len(out) < n:
            part = self.sock.recv(n - len(out))
            if not part:
                raise ConnectionError("the controller closed the connection")
            out += part
        return bytes(out)

    def settimeout(self, seconds: float) -> None:
        """Ignored: the link sets the timeout of each reply itself."""

    def close(self) -> None:
        self.sock.close()


class NanonisLink:
    """One TCP connection to the controller's programming interface.

    Parameters
    ----------
    config : NanonisConfig
        Host, port and timeout.
    module : module, optional
        ``nanonis_spm`` or a stand-in with its ``Nanonis`` class; default: import it.
    """

    def __init__(self, config: NanonisConfig, *, module: Any = None):
        self.config = config
        self._client_class = load_client(module)
        self._sock: _Socket | None = None
        self._client = None
        self.calls = 0
        self.reconnect()

    @property
    def connected(self) -> bool:
        return self._client is not None

    def reconnect(self) -> None:
        """(Re)open the connection; :class:`NanonisError` in one line if nobody answers."""
        self.close()
        c = self.config
        try:
            sock = socket.create_connection((c.host, c.port), timeout=c.timeout)
        except OSError as exc:
            reason = exc.strerror or str(exc) or type(exc).__name__
            raise NanonisError(f"cannot reach the Nanonis controller at {c.address}: {reason} (is its TCP "
                               "Programming Interface on, at this port?)") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = _Socket(sock)
        self._client = self._client_class(self._sock)

    def call(self, command: str, *args: Any, duration: float = 0.0) -> list:
        """Send ``command`` (a ``Nanonis`` method name such as ``"FolMe_XYPosSet"``) and
        return its return values; ``duration`` (s) is how long the command itself runs,
        added to the timeout of its reply."""
        name = command.replace("_", ".", 1)
        if self._client is None:
            raise NanonisError(f"{name}: the connection to the Nanonis controller at {self.config.address} "
                               "is closed")
        self._sock.sock.settimeout(self.config.timeout + max(0.0, duration))
        self.calls += 1
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                reply = getattr(self._client, command)(*args)
        except TimeoutError:
            self.close()
            raise NanonisError(f"{name}: no reply from the Nanonis controller at {self.config.address} within "
                               f"{self.config.timeout + duration:.3g} s") from None
        except (OSError, struct.error, ValueError, IndexError, UnicodeError) as exc:  # a garbled or cut reply
            self.close()
            raise NanonisError(f"{name}: lost the Nanonis controller at {self.config.address}: "
                               f"{_first_line(exc)}") from None
        except BaseException:   # Ctrl-C mid-reply: the stream is out of step
            self.close()
            raise
        if not reply:
            self.close()
            raise NanonisError(f"{name}: the Nanonis controller at {self.config.address} answered another "
                               "command")
        error, _, values = reply
        if error:
            raise NanonisError(f"the Nanonis controller refused {name}: {_first_line(error)}")
        return list(values)

    def close(self) -> None:
        sock, self._sock, self._client = self._sock, None, None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()


def _first_line(text: Any) -> str:
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    return lines[0] if lines else type(text).__name__


__all__ = ["NanonisError", "NanonisLink", "load_client"]

"""A stand-in for a Nanonis controller: its TCP programming interface on 127.0.0.1.

:class:`FakeNanonis` listens on an ephemeral port and speaks the documented protocol:
a request is a 40-byte header (the command name NUL-padded to 32 bytes, the body size
as a big-endian int32, the send-response flag as a uint16, two zero bytes) and a body
of big-endian arguments; a reply is the same header (four zero bytes after the size)
and a body of the return values, then the error status (uint32), the error text's size
(int32) and the text. Arguments are decoded by each command's documented types, and a
body that does not match them is answered with an error and recorded in ``violations``.

Behind it one simulated microscope, in Nanonis units (m, m/s):

- XY moves by follow-me only (instantly); Z by ``ZCtrl.ZPosSet``, refused while the Z
  controller is on; with the controller on, Z sits on ``surface(x, y)``;
- the signals of ``Signals.ValsGet`` are ``signal(index, x, y, z, surface)``: by
  default S_n (index 0) is the deflection, 1 V per 89 nm of Z below the surface, S_l
  (index 1) 1 mV per µm of X, and index 30 is Z;
- a scan (``Scan.Action`` start) fills the frame at once with ``surface`` at the pixel
  centres, the pixels coerced to a multiple of 16 as the scan module does, row 0 the
  first line scanned.

Everything is recorded: ``calls`` (command name and decoded arguments, in order),
``track`` (``(x, y, z, on)`` after every command) and ``violations`` (Z beyond the
limits, XY beyond the piezo range, a malformed request). ``refuse_next``,
``hang_up_next`` and ``silent_next`` make the next call of a command fail.
"""

from __future__ import annotations

import socketserver
import struct
import threading
from collections.abc import Callable

import numpy as np

HEADER = 40

#: Argument and return types of every command the fake knows (the nanonis-spm notation).
COMMANDS: dict[str, tuple[list[str], list[str]]] = {
    "ZCtrl.LimitsGet": ([], ["f", "f"]),
    "ZCtrl.OnOffGet": ([], ["I"]),
    "ZCtrl.OnOffSet": (["I"], []),
    "ZCtrl.ZPosGet": ([], ["f"]),
    "ZCtrl.ZPosSet": (["f"], []),
    "ZCtrl.SetpntSet": (["f"], []),
    "Piezo.RangeGet": ([], ["f", "f", "f"]),
    "FolMe.XYPosGet": (["I"], ["d", "d"]),
    "FolMe.XYPosSet": (["d", "d", "I"], []),
    "FolMe.SpeedSet": (["f", "I"], []),
    "Signals.ValsGet": (["+*i", "I"], ["i", "*f"]),
    "Scan.FrameSet": (["f", "f", "f", "f", "f"], []),
    "Scan.BufferSet": (["+*i", "i", "i"], []),
    "Scan.SpeedSet": (["f", "f", "f", "f", "H", "f"], []),
    "Scan.Action": (["H", "I"], []),
    "Scan.StatusGet": ([], ["I"]),
    "Scan.WaitEndOfScan": (["i"], ["I", "I", "*-c"]),
    "Scan.FrameDataGrab": (["I", "I"], ["i", "*-c", "i", "i", "2f", "I"]),
}

K_N = 89e-9  # m of deflection per volt of S_n


def default_surface(x: float, y: float) -> float:
    """Z (m) where the tip touches: a plane at 1 µm with a 40 nm bump at (2, 2) µm."""
    return 1.0e-6 + 40e-9 * float(np.exp(-((x - 2e-6) ** 2 + (y - 2e-6) ** 2) / (0.3e-6) ** 2))


def default_signal(index: int, x: float, y: float, z: float, surface: float) -> float:
    if index == 0:
        return max(0.0, surface - z) / K_N
    if index == 1:
        return 1e3 * x
    if index == 30:
        return z
    return 0.0


def _decode(body: bytes, types: list[str]) -> tuple[list, int]:
    out, at = [], 0
    for t in types:
        if t == "+*i":
            (n,) = struct.unpack_from(">i", body, at)
            at += 4
            out.append(list(struct.unpack_from(f">{n}i", body, at)))
            at += 4 * n
        else:
            (v,) = struct.unpack_from(">" + t, body, at)
            at += struct.calcsize(t)
            out.append(v)
    return out, at


def _encode(types: list[str], values: list) -> bytes:
    out = bytearray()
    for t, v in zip(types, values):
        if t == "*f":
            out += struct.pack(f">{len(v)}f", *v)
        elif t == "*-c":
            out += v.encode()
        elif t == "2f":
            a = np.asarray(v, ">f4")
            out += a.tobytes()
        else:
            out += struct.pack(">" + t, v)
    return bytes(out)


def _reply(name: str, body: bytes, error: str = "") -> bytes:
    text = error.encode()
    body = body + struct.pack(">Ii", 1 if error else 0, len(text)) + text
    return name.encode().ljust(32, b"\0") + struct.pack(">I", len(body)) + bytes(4) + body


class FakeNanonis:
    """The fake controller; ``with FakeNanonis() as fake:`` serves on ``fake.port``."""

    def __init__(self, *, surface: Callable[[float, float], float] = default_surface,
                 signal: Callable[..., float] = default_signal, z_limits=(5e-6, -5e-6), xy_limit=50e-6,
                 xy=(0.0, 0.0), engaged: bool = True):
        self.surface, self.signal = surface, signal
        self.z_high, self.z_low = z_limits
        self.xy_limit = xy_limit
        self.x, self.y = xy
        self.on = engaged
        self.z = surface(*xy)
        self.setpoint = 0.0
        self.speed = (1e-6, 0)
        self.frame = (0.0, 0.0, 1e-6, 1e-6, 0.0)
        self.buffer = ([30], 64, 64)
        self.scan: tuple[np.ndarray, int] | None = None
        self.calls: list[tuple[str, tuple]] = []
        self.track: list[tuple[float, float, float, bool]] = []
        self.violations: list[str] = []
        self.connections = 0
        self._refuse: dict[str, str] = {}
        self._hang_up: set[str] = set()
        self._silent: set[str] = set()
        self._lock = threading.Lock()
        fake = self

        class Handler(socketserver.BaseRequestHandler):
            def handle(self):
                fake.connections += 1
                fake._serve(self.request)

        self._server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Handler)
        self._server.daemon_threads = True
        self.port = self._server.server_address[1]
        self._thread = threading.Thread(target=self._server.serve_forever, args=(0.01,), daemon=True)
        self._thread.start()

    # -- failures ---------------------------------------------------------------------------
    def refuse_next(self, command: str, message: str = "Command refused by the fake") -> None:
        """The next call of ``command`` is answered with this error."""
        self._refuse[command] = message

    def hang_up_next(self, command: str) -> None:
        """The next call of ``command`` closes the connection without a reply."""
        self._hang_up.add(command)

    def silent_next(self, command: str) -> None:
        """The next call of ``command`` gets no reply (the connection stays open)."""
        self._silent.add(command)

    # -- inspection -------------------------------------------------------------------------
    def names(self) -> list[str]:
        return [c for c, _ in self.calls]

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- the protocol -----------------------------------------------------------------------
    def _serve(self, sock) -> None:
        while True:
            head = _read(sock, HEADER)
            if head is None:
                return
            name = head[:32].rstrip(b"\0").decode()
            size, flag = struct.unpack(">iH", head[32:38])
            body = _read(sock, size) if size else b""
            if body is None:
                return
            with self._lock:
                if name in self._hang_up:
                    self._hang_up.discard(name)
                    self.calls.append((name, ("hung up",)))
                    sock.close()
                    return
                if name in self._silent:
                    self._silent.discard(name)
                    self.calls.append((name, ("no reply",)))
                    continue
                reply = self._answer(name, head, body)
            if flag:
                sock.sendall(reply)

    def _answer(self, name: str, head: bytes, body: bytes) -> bytes:
        if head[38:40] != b"\0\0":
            self.violations.append(f"{name}: header bytes 38-39 are not zero")
        if name not in COMMANDS:
            self.calls.append((name, ()))
            return _reply(name, b"", f"Unknown command {name}")
        arg_types, ret_types = COMMANDS[name]
        try:
            args, used = _decode(body, arg_types)
        except struct.error:
            used, args = -1, []
        if used != len(body):
            self.violations.append(f"{name}: a body of {len(body)} bytes does not match {arg_types}")
            self.calls.append((name, ()))
            return _reply(name, b"", "Malformed arguments")
        self.calls.append((name, tuple(args)))
        if name in self._refuse:
            return _reply(name, b"", self._refuse.pop(name))
        error, values = self._run(name, args)
        self.track.append((self.x, self.y, self.z, self.on))
        return _reply(name, b"" if error else _encode(ret_types, values), error)

    def _run(self, name: str, a: list) -> tuple[str, list]:  # noqa: C901 - one branch a command
        if name == "ZCtrl.LimitsGet":
            return "", [self.z_high, self.z_low]
        if name == "ZCtrl.OnOffGet":
            return "", [int(self.on)]
        if name == "ZCtrl.OnOffSet":
            self.on = bool(a[0])
            self._follow()
            return "", []
        if name == "ZCtrl.ZPosGet":
            return "", [self.z]
        if name == "ZCtrl.ZPosSet":
            if self.on:
                return "Switch off the Z-controller to set the Z position", []
            if not self.z_low <= a[0] <= self.z_high:
                self.violations.append(f"Z = {a[0]:.4g} m beyond the limits [{self.z_low:g}, {self.z_high:g}]")
                return "Z position beyond the limits", []
            self.z = a[0]
            return "", []
        if name == "ZCtrl.SetpntSet":
            self.setpoint = a[0]
            return "", []
        if name == "Piezo.RangeGet":
            return "", [2 * self.xy_limit, 2 * self.xy_limit, self.z_high - self.z_low]
        if name == "FolMe.XYPosGet":
            return "", [self.x, self.y]
        if name == "FolMe.XYPosSet":
            if max(abs(a[0]), abs(a[1])) > self.xy_limit:
                self.violations.append(f"XY = ({a[0]:.4g}, {a[1]:.4g}) m beyond the piezo range")
            self.x, self.y = a[0], a[1]
            self._follow()
            return "", []
        if name == "FolMe.SpeedSet":
            self.speed = (a[0], a[1])
            return "", []
        if name == "Signals.ValsGet":
            values = [self.signal(i, self.x, self.y, self.z, self.surface(self.x, self.y)) for i in a[0]]
            return "", [len(values), values]
        if name.startswith("Scan."):
            return self._scan(name, a)
        return f"the fake does not run {name}", []

    def _scan(self, name: str, a: list) -> tuple[str, list]:
        if name == "Scan.FrameSet":
            self.frame = tuple(a)
        elif name == "Scan.BufferSet":
            self.buffer = (a[0], max(16, 16 * round(a[1] / 16)), a[2])
        elif name == "Scan.SpeedSet":
            pass
        elif name == "Scan.Action" and a[0] == 0:
            self.scan = (self._image(up=bool(a[1])), int(a[1]))
        elif name == "Scan.StatusGet":
            return "", [0]
        elif name == "Scan.WaitEndOfScan":
            return "", [0 if self.scan is not None else 1, 0, ""]
        elif name == "Scan.FrameDataGrab":
            if self.scan is None or a[0] not in self.buffer[0]:
                return "No scan data for this channel", []
            data, up = self.scan
            return "", [5, "Z (m)", data.shape[0], data.shape[1], data, up]
        return "", []

    def _image(self, up: bool) -> np.ndarray:
        cx, cy, w, h, _ = self.frame
        _, px, lines = self.buffer
        xs = cx - w / 2 + (np.arange(px) + 0.5) * w / px
        ys = cy - h / 2 + (np.arange(lines) + 0.5) * h / lines
        if not up:
            ys = ys[::-1]
        if self.on:
            data = np.array([[self.surface(x, y) for x in xs] for y in ys])
        else:
            data = np.full((lines, px), self.z)
        self.x, self.y = xs[0], ys[-1]
        self._follow()
        return data

    def _follow(self) -> None:
        if self.on:
            self.z = self.surface(self.x, self.y)


def _read(sock, n: int) -> bytes | None:
    out = bytearray()
    while len(out) < n:
        try:
            part = sock.recv(n - len(out))
        except OSError:
            return None
        if not part:
            return None
        out += part
    return bytes(out)

"""Stopping a run by a signal: Ctrl-C (SIGINT) and SIGTERM while a run engine runs.

A signal stops the run: its handler raises ``KeyboardInterrupt`` or the engine's
``Terminated`` in the main thread, and the engine cleans up (parks the instrument, sends
``stop``, closes the log). From the moment the engine takes the stop in hand (the first
statement of its ``except`` or ``finally``, a plain attribute store that no signal
handler can run before) every further SIGINT and SIGTERM is held until the clean-up
ends: a second Ctrl-C 1 ms after the first, or one while a completed run closes its log,
cannot cut the log's ``/stop`` record or its closing. A signal held while a run that had
not been stopped cleaned up is raised after the clean-up, so it still stops the program.

Until then a further signal raises again, as Python's own handler does. A
``KeyboardInterrupt`` swallowed by library code that calls back into Python and clears
its errors (seen inside ``enum``'s ``__getattr__`` during a simulated push) is not the
end of Ctrl-C either: the signal stays pending and the engine raises it again before its
next message (:meth:`StopSignals.check`), or after the clean-up of a run that then
completed. Two Ctrl-C a millisecond apart can reach Python as one call of the handler,
so the second cannot be counted on to repeat a swallowed first (a run in CI went on to
its end that way).

Only the main thread handles signals. SIGINT is taken over only from Python's default
handler: one ignored (a sweep's worker) or the host program's own is left alone.

A program that ends once a run is stopped by a signal (the ``nanoasm`` command) calls
:func:`ignore_after_stop`: the handlers are then not restored after such a stop, the
signals stay ignored, so a second Ctrl-C a millisecond after the first cannot cut what
the program still prints or closes on its way out (it used to: the line naming the
written log went missing).
"""

from __future__ import annotations

import signal
import threading


_ignore_after_stop = False


def ignore_after_stop(enabled: bool = True) -> None:
    """After a run stopped by SIGINT or SIGTERM, leave both ignored rather than restore
    the handlers from before (for a process that ends then)."""
    global _ignore_after_stop
    _ignore_after_stop = enabled


class StopSignals:
    """SIGINT and SIGTERM for one run: :meth:`install`; set :attr:`stopping` when the
    run's stop or end is in hand (further signals are held from then on); :meth:`restore`
    after the clean-up, then :meth:`raise_held`. ``terminated`` is what SIGTERM raises."""

    def __init__(self, terminated: type[BaseException]):
        self.terminated = terminated
        self.stopping = False
        self.held: int | None = None          # the first signal received while stopping
        self.pending: int | None = None       # a signal raised while running (perhaps swallowed)
        self._previous: dict[int, object] = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self._previous[signal.SIGINT] = signal.signal(signal.SIGINT, self._handle)
        self._previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, self._handle)

    def _handle(self, signum, frame) -> None:
        if self.stopping:
            if self.held is None:
                self.held = signum
            return
        if self.pending is None:
            self.pending = signum
        self._raise(signum)

    def check(self) -> None:
        """Raise again a signal received while running whose exception never reached
        the engine (swallowed on its way); nothing if there is none or the stop is in hand."""
        if self.pending is not None and not self.stopping:
            self._raise(self.pending)

    def _raise(self, signum: int) -> None:
        raise KeyboardInterrupt if signum == signal.SIGINT else self.terminated()

    def restore(self, by_signal: bool = False) -> None:
        """The handlers from before :meth:`install` (``by_signal``: the run was stopped
        by a signal; both stay ignored then if :func:`ignore_after_stop` was asked for)."""
        ignore = by_signal and _ignore_after_stop
        for sig, handler in self._previous.items():
            signal.signal(sig, signal.SIG_IGN if ignore else handler)
        self._previous.clear()

    def raise_held(self) -> None:
        """Raise the signal held during a clean-up, or one received while running that
        never stopped the run (swallowed), if any (after :meth:`restore`)."""
        signum = self.held if self.held is not None else self.pending
        self.held = self.pending = None
        if signum is not None:
            self._raise(signum)

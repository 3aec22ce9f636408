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

A signal that arrives while a module is being imported is not raised there: an
extension module that calls back into Python while it loads (OMPL's, through nanobind)
cannot carry an exception out of its initialisation, and the process aborts (a CI run:
Ctrl-C in the first 10 ms of OMPL's import). It is delivered again to the main thread
every 20 ms until the import has ended, and the engine's next message raises it too
(:meth:`StopSignals.check`). A program can have the same for the time before a run:
:func:`interrupt_outside_imports` as its SIGINT handler (the ``nanoasm`` command).

Only the main thread handles signals. SIGINT is taken over only from Python's default
handler (or :func:`interrupt_outside_imports`): one ignored (a sweep's worker) or the
host program's own is left alone.

A program that ends once a run is stopped by a signal (the ``nanoasm`` command) calls
:func:`ignore_after_stop`: the handlers are then not restored after such a stop, the
signals stay ignored, so a second Ctrl-C a millisecond after the first cannot cut what
the program still prints or closes on its way out (it used to: the line naming the
written log went missing).
"""

from __future__ import annotations

import _thread
import signal
import threading


_ignore_after_stop = False


def ignore_after_stop(enabled: bool = True) -> None:
    """After a run stopped by SIGINT or SIGTERM, leave both ignored rather than restore
    the handlers from before (for a process that ends then)."""
    global _ignore_after_stop
    _ignore_after_stop = enabled


#: How soon a signal that arrived inside an import is delivered again.
AGAIN_SECONDS = 0.02

_owed: int | None = None      # a signal that arrived inside an import and is not raised yet
_armed = False                # a delivery of it is on its way


def interrupt_outside_imports(signum, frame) -> None:
    """A SIGINT handler for a program: KeyboardInterrupt, as Python's own handler,
    except inside an import, where it is raised once the import has ended. A run's
    engine takes SIGINT over from it as from Python's own, and with it a Ctrl-C owed."""
    if _importing(frame):
        _owe(signum)
        return
    _paid()
    raise KeyboardInterrupt


def _owe(signum: int) -> None:
    """Deliver ``signum`` to the main thread again in a moment, through whatever handler
    handles it then (none if it is ignored), until it is raised."""
    global _owed, _armed
    _owed = signum
    if _armed:
        return
    _armed = True

    def deliver():
        global _armed
        _armed = False
        if _owed is not None:
            _thread.interrupt_main(_owed)
    timer = threading.Timer(AGAIN_SECONDS, deliver)
    timer.daemon = True
    timer.start()


def _paid() -> None:
    global _owed
    _owed = None


def _importing(frame) -> bool:
    """Whether ``frame`` runs inside an import (a frame of importlib's bootstrap below it)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib._bootstrap"):
            return True
        frame = frame.f_back
    return False


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
        if signal.getsignal(signal.SIGINT) in (signal.default_int_handler, interrupt_outside_imports):
            self._previous[signal.SIGINT] = signal.signal(signal.SIGINT, self._handle)
            if _owed is not None:               # a Ctrl-C inside an import before the run
                self.pending = _owed
        self._previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, self._handle)

    def _handle(self, signum, frame) -> None:
        if self.stopping:
            if self.held is None:
                self.held = signum
            return
        if self.pending is None:
            self.pending = signum
        if _importing(frame):
            _owe(signum)                        # or check() at the next message, if sooner
            return
        self._raise(signum)

    def check(self) -> None:
        """Raise again a signal received while running whose exception never reached
        the engine (swallowed on its way); nothing if there is none or the stop is in hand."""
        if self.pending is not None and not self.stopping:
            self._raise(self.pending)

    def _raise(self, signum: int) -> None:
        _paid()
        raise KeyboardInterrupt if signum == signal.SIGINT else self.terminated()

    def restore(self, by_signal: bool = False) -> None:
        """The handlers from before :meth:`install` (``by_signal``: the run was stopped
        by a signal; both stay ignored then if :func:`ignore_after_stop` was asked for)."""
        ignore = by_signal and _ignore_after_stop
        for sig, handler in self._previous.items():
            signal.signal(sig, signal.SIG_IGN if ignore else handler)
        self._previous.clear()
        _paid()                                 # the run has had it (raise_held for one that ended)

    def raise_held(self) -> None:
        """Raise the signal held during a clean-up, or one received while running that
        never stopped the run (swallowed), if any (after :meth:`restore`)."""
        signum = self.held if self.held is not None else self.pending
        self.held = self.pending = None
        if signum is not None:
            self._raise(signum)

"""Logging helpers. The run's handlers are configured by Hydra from conf/hydra/job_logging/sdexp.yaml:
INFO to stdout, warnings and errors to stderr, everything to the run folder's cli.log."""
from __future__ import annotations

import logging


class BelowWarning(logging.Filter):
    """Lets through the records below WARNING (those go to stderr instead)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < logging.WARNING


def to_log_files(message: str, level: int = logging.ERROR, name: str = "sdexp") -> None:
    """``message`` into the log files only (the console has it already, e.g. a one-line error)."""
    record = logging.LogRecord(name, level, __file__, 0, message, None, None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


# ------------------------------------------------------------------------------ long phases

# A phase logs a progress line when it has done another PROGRESS_STEP of its total and at least
# MIN_INTERVAL s have passed since its last line (so a phase of a few seconds says only its start
# and end), and, from a background thread, whenever MAX_INTERVAL s pass without a line (a phase
# with no known total, like meshing, or a slow stretch of one with a total).
PROGRESS_STEP = 0.1
MIN_INTERVAL = 5.0
MAX_INTERVAL = 30.0


def on_terminal() -> bool:
    """Whether progress bars can be drawn: tqdm draws on stderr, and only on a terminal."""
    import sys
    stream = sys.stderr
    return bool(stream is not None and hasattr(stream, "isatty") and stream.isatty())


class Phase:
    """A long phase of a run (meshing, data generation, a network's training, a flight).

    Its start and its end (time taken, rate in ``unit``/s) are logged (console and cli.log); in
    between, a tqdm bar on a terminal, else progress lines (``PROGRESS_STEP``, ``MIN_INTERVAL``,
    ``MAX_INTERVAL``), so a run whose output is redirected, as on a cluster, can be followed in
    its log. ``enabled=False``: silent. The interface is the part of tqdm's the library uses:
    ``update(n)``, ``set_postfix(**kw)``, ``close()``, a context manager; ``iterate(it)`` wraps
    an iterable. ``clock`` (tests) replaces time.perf_counter; ``bar`` forces (True) or rules
    out (False) the terminal bar. ``quiet_for``: a phase that is mostly quick (a compile the
    caches usually spare) says nothing, its end included, unless it takes longer than that many
    seconds: then a line says it started that long ago, and it goes on as any phase."""

    def __init__(self, desc: str, total: float | None = None, unit: str = "it", initial: int = 0,
                 enabled: bool = True, bar: bool | None = None, logger: logging.Logger | None = None,
                 clock=None, heartbeat: bool = True, quiet_for: float | None = None):
        import threading
        import time
        self.desc, self.total, self.unit = desc, total, unit
        self.n = self.start_n = int(initial)
        self.enabled = enabled
        self.log = logger or logging.getLogger("sdexp.progress")
        self.clock = clock or time.perf_counter
        self.postfix = ""
        self.closed = False
        self._bar = None
        self._lock = threading.Lock()
        self._stop = None
        self.quiet_for = quiet_for
        self.said = not quiet_for   # a quiet phase's lines wait until it has taken quiet_for s
        if not enabled:
            return
        self.t0 = self._last = self.clock()
        self._next = self._step_after(self._frac())
        self._size = "" if not total else f" ({_count(total - initial)} {unit}{' to go' if initial else ''})"
        if self.said:
            self.log.info(f"sdexp: {desc}: started{self._size}")
        if self.said and (on_terminal() if bar is None else bar):
            from tqdm import tqdm
            self._bar = tqdm(total=total, initial=initial, desc=desc, unit=unit, leave=False)
        elif heartbeat or not self.said:
            self._stop = threading.Event()
            threading.Thread(target=self._beat, name=f"sdexp progress: {desc}", daemon=True).start()

    # -------------------------------------------------------------------------------- tqdm's part
    def update(self, n: int = 1) -> None:
        if not self.enabled:
            return
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
            return
        frac = self._frac()
        # no line at 100%: the closing line follows
        if self.said and frac is not None and self._next <= frac + 1e-9 < 1 and self.clock() - self._last >= MIN_INTERVAL:
            self._next = self._step_after(frac)
            self._say()

    def set_postfix(self, **kw) -> None:
        """Shown in the bar, and at the end of the progress lines and the closing line."""
        self.postfix = ", ".join(f"{k} {v}" for k, v in kw.items())
        if self._bar is not None:
            self._bar.set_postfix(**kw)

    def iterate(self, iterable):
        """Yield the items of ``iterable``, one update after each; the phase closes at its end
        or when the loop stops early."""
        try:
            for item in iterable:
                yield item
                self.update()
        finally:   # also when the loop is left early (the generator is closed then)
            self.close()

    def close(self, outcome: str = "") -> None:
        """The closing line: time taken and rate; ``outcome`` adds what the phase made."""
        if not self.enabled or self.closed:
            return
        secs = self.clock() - self.t0
        done = self.n - self.start_n
        rate = f", {_rate(done, secs, self.unit)}" if done else ""
        extra = "".join(f"; {s}" for s in (outcome, self.postfix) if s)
        self._finish(f"done in {_seconds(secs)}{rate}{extra}")

    @property
    def elapsed(self) -> float:
        """Seconds since the phase started (0 when it is silent)."""
        return self.clock() - self.t0 if self.enabled else 0.0

    def abort(self) -> None:
        """The closing line of a phase an error stopped (a no-op once it is closed)."""
        if self.enabled and not self.closed:
            self._finish(f"stopped after {_seconds(self.clock() - self.t0)}")

    def _finish(self, line: str) -> None:
        with self._lock:   # a quiet phase is either announced and closed with a line, or silent
            self.closed = True
        if self._stop is not None:
            self._stop.set()
        if self._bar is not None:
            self._bar.close()
        if self.said:
            self.log.info(f"sdexp: {self.desc}: {line}")

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        self.abort() if exc_type is not None else self.close()
        return False

    # -------------------------------------------------------------------------------- log lines
    def _frac(self) -> float | None:
        return self.n / self.total if self.total else None

    @staticmethod
    def _step_after(frac: float | None) -> float:
        """The next multiple of PROGRESS_STEP above ``frac`` (10%, 20%, ...: steady steps)."""
        import math
        return math.inf if frac is None else (math.floor(frac / PROGRESS_STEP + 1e-9) + 1) * PROGRESS_STEP

    def _say(self) -> None:
        with self._lock:
            now = self.clock()
            self._last = now
            secs, done = now - self.t0, self.n - self.start_n
            frac = self._frac()
            parts = []
            if frac is not None:
                parts.append(f"{100 * frac:.0f}% ({_count(self.n)}/{_count(self.total)} {self.unit})")
            elif done:
                parts.append(f"{_count(self.n)} {self.unit}")
            parts.append(f"{_seconds(secs)} so far")
            if done:
                parts.append(_rate(done, secs, self.unit))
                if frac is not None and self.total > self.n:
                    parts.append(f"about {_seconds((self.total - self.n) * secs / done)} left")
            if self.postfix:
                parts.append(self.postfix)
            self.log.info(f"sdexp: {self.desc}: {', '.join(parts)}")

    def _beat(self) -> None:
        while not self._stop.wait(1.0):
            if not self.said:
                if self.clock() - self.t0 >= self.quiet_for:
                    self._announce()
            elif self.clock() - self._last >= MAX_INTERVAL:
                self._say()

    def _announce(self) -> None:
        """A quiet phase's first line, once it has taken quiet_for s."""
        with self._lock:
            if self.closed:
                return
            self.said, self._last = True, self.clock()
            extra = f"; {self.postfix}" if self.postfix else ""
            self.log.info(f"sdexp: {self.desc}: started {_seconds(self._last - self.t0)} ago{self._size}{extra}")


def _count(n: float) -> str:
    return f"{n:,.0f}" if float(n).is_integer() else f"{n:,.1f}"


def _seconds(s: float) -> str:
    return f"{s:.1f} s" if s < 120 else f"{s / 60:.1f} min"


def _rate(done: float, secs: float, unit: str) -> str:
    """Rate as unit/s, or s/unit when one takes longer than a second (an epoch)."""
    if secs <= 0:
        return f"{_count(done)} {unit}"
    per = done / secs
    if per >= 100:
        return f"{per:,.0f} {unit}/s"
    return f"{per:.3g} {unit}/s" if per >= 1 else f"{secs / done:.3g} s/{unit.rstrip('s')}"


# ------------------------------------------------------------------------------ numba's compiling

NUMBA_QUIET = 3.0   # s of compiling in a row before the log says so
NUMBA_PAUSE = 2.0   # s without a compile that end a run of compiles

_numba_said = None


class NumbaCompiles:
    """numba compiles each function on its first call unless its on-disk cache has it: on a new
    machine, after a numba upgrade or a code change, a run's first minute (several on a loaded
    machine) goes to compiling. Each run of compiles (none NUMBA_PAUSE s apart) is a quiet
    Phase: said once it has taken NUMBA_QUIET s, naming the function compiling then, and closed
    with how many it compiled (its time includes the pause that ends it). ``on_start`` and
    ``on_end`` are numba's compile events'."""

    def __init__(self, quiet: float = NUMBA_QUIET, pause: float = NUMBA_PAUSE):
        import threading
        self.quiet, self.pause = quiet, pause
        self._lock = threading.Lock()
        self.phase: Phase | None = None
        self._depth = 0
        self._timer = None

    def on_start(self, name: str) -> None:
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
            if self.phase is None:
                self.phase = Phase("numba: compiling on first use (cached on disk for the runs after)",
                                   unit="functions", quiet_for=self.quiet)
            self._depth += 1
            if self._depth == 1:   # the outermost: the function the run called
                self.phase.set_postfix(now=name)

    def on_end(self) -> None:
        import threading
        with self._lock:
            self._depth -= 1
            self.phase.update()
            if self._depth == 0:
                self._timer = threading.Timer(self.pause, self._close)
                self._timer.daemon = True
                self._timer.start()

    def _close(self) -> None:
        with self._lock:
            if self._depth == 0 and self.phase is not None:
                self.phase.postfix = ""
                self.phase.close()
                self.phase = None


def say_numba_compiles() -> None:
    """NumbaCompiles on this process's numba compiles (once; a no-op without numba)."""
    global _numba_said
    if _numba_said is not None:
        return
    try:
        from numba.core import event
    except ImportError:
        return
    compiles = NumbaCompiles()

    class Listener(event.Listener):
        def on_start(self, ev):
            f = ev.data["dispatcher"].py_func
            compiles.on_start(f"{f.__module__}.{f.__qualname__}")

        def on_end(self, ev):
            compiles.on_end()

    _numba_said = compiles
    event.register("numba:compile", Listener())

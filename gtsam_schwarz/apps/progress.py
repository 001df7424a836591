"""Progress of long commands on stderr, never on stdout (which may carry a table or one JSON object).

On a terminal: a live tqdm bar (steps done, elapsed time, the running step and its latest
iteration); without tqdm, or when stderr is a file or a pipe: plain lines, one when a step starts
and ends and at most one every ``interval`` seconds in between. ``enabled=False`` (``--quiet``)
prints nothing. A broken or closed stderr silently turns the display off.
"""

from __future__ import annotations

import contextlib
import sys
import time

PLAIN_INTERVAL = 5.0  # seconds between two plain progress lines inside one step
LIVE_INTERVAL = 0.1  # seconds between two redraws of the live bar


def _tqdm():
    try:
        from tqdm import tqdm
    except ImportError:  # an optional nicety: plain lines without it
        return None
    return tqdm


class Progress:
    """``with Progress("compare", total=7) as p: p.start("gtsam-lm"); p.note("iteration 3"); p.done()``."""

    def __init__(self, label: str, total: int | None = None, *, enabled: bool = True, stream=None,
                 live: bool | None = None, interval: float = PLAIN_INTERVAL, clock=time.monotonic):
        self.label, self.total = label, total
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.interval, self.clock = interval, clock
        self.count, self.name = 0, None
        self._t0 = self._step_t0 = self._last = clock()
        self._bar = None
        if enabled:
            if live is None:
                live = bool(getattr(self.stream, "isatty", lambda: False)())
            tqdm = _tqdm() if live else None
            if tqdm is not None:
                try:
                    fmt = ("{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]" if total
                           else "{desc}: [{elapsed}{postfix}]")
                    self._bar = tqdm(total=total, desc=label, file=self.stream, leave=False, dynamic_ncols=True,
                                     bar_format=fmt, mininterval=LIVE_INTERVAL)
                except OSError:
                    self.enabled = False

    @property
    def live(self) -> bool:
        return self._bar is not None

    # -- output, robust against a closed stderr --------------------------------------------------
    def _line(self, text: str) -> None:
        if not self.enabled:
            return
        try:
            if self._bar is not None:
                self._bar.write(f"{self.label}: {text}", file=self.stream)
            else:
                print(f"{self.label}: {text}", file=self.stream, flush=True)
        except (OSError, ValueError):  # broken pipe or closed stream: stop showing progress
            self.enabled = False
        self._last = self.clock()

    def _bar_call(self, method: str, *args, **kwargs) -> None:
        try:
            getattr(self._bar, method)(*args, **kwargs)
        except (OSError, ValueError):
            self.enabled = False
            self._bar = None

    def _where(self) -> str:
        return f"[{self.count + 1}/{self.total}] " if self.total else ""

    # -- the steps ---------------------------------------------------------------------------------
    def start(self, name: str) -> None:
        """A step begins (a solver of ``compare``; the solve of ``solve``)."""
        self.name, self._step_t0 = name, self.clock()
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar_call("set_postfix_str", name)
        else:
            self._line(f"{self._where()}{name} ...")

    def note(self, text: str) -> None:
        """Where the running step is (e.g. its latest iteration): live always, plain every ``interval`` s."""
        if not self.enabled:
            return
        prefix = f"{self.name} " if self.name else ""
        if self._bar is not None:
            now = self.clock()
            redraw = now - self._last >= LIVE_INTERVAL
            if redraw:
                self._last = now
            self._bar_call("set_postfix_str", f"{prefix}{text}", refresh=redraw)
        elif self.clock() - self._last >= self.interval:
            self._line(f"{self._where()}{prefix}{text} ({self.clock() - self._step_t0:.0f} s)")

    def done(self, text: str = "") -> None:
        """The running step has finished."""
        if self.enabled:
            seconds = self.clock() - self._step_t0
            if self._bar is not None:
                self._bar_call("update", 1)
            elif self.name is not None:
                self._line(f"{self._where()}{self.name} done in {seconds:.1f} s{'; ' + text if text else ''}")
        self.count += 1
        self.name = None

    @contextlib.contextmanager
    def suspended(self):
        """Around output to another stream of the same terminal (a table on stdout): the live bar is
        cleared first and drawn again after."""
        if self._bar is None:
            yield
            return
        try:
            with type(self._bar).external_write_mode(file=self.stream):
                yield
        except OSError:
            self.enabled = False

    def close(self) -> None:
        if self._bar is not None:
            self._bar_call("close")
            self._bar = None

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


"""Wall-clock and CPU time per step, recorded in order: the one timer of ffrecon (pipeline stages, and the
steps inside COLMAP, refinement and the splat)."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

try:
    import resource
except ImportError:  # not on Windows: the process's own CPU time only (no children)
    resource = None


def cpu_seconds() -> float:
    """User + system CPU seconds so far of this process (all its threads) and of its children that ended and
    were waited for (COLMAP's and ffmpeg's subprocesses, say); :func:`time.process_time` where the ``resource``
    module is missing (no children then).

    The whole process's: a stage that runs beside another in a second thread counts the other's CPU too.

    >>> cpu_seconds() >= 0
    True
    """
    if resource is None:
        return time.process_time()
    me, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + children.ru_utime + children.ru_stime


@dataclass(frozen=True)
class Clock:
    """A moment of the run: ``wall`` (:func:`time.perf_counter`) and ``cpu`` (:func:`cpu_seconds`) then, and what
    it was (``origin``: the process's start, a call).

    >>> start = Clock.now()
    >>> wall, cpu = start.since()
    >>> wall >= 0 and cpu >= 0
    True
    """

    wall: float
    cpu: float
    origin: str = "now"

    @classmethod
    def now(cls, origin: str = "now") -> "Clock":
        return cls(time.perf_counter(), cpu_seconds(), origin)

    @classmethod
    def process_start(cls) -> "Clock | None":
        """When this process started, from the kernel (``/proc/self/stat``'s start time, in clock ticks of 10 ms
        since boot, against ``CLOCK_BOOTTIME``), with no CPU spent yet; None where ``/proc`` is missing."""
        try:
            with open("/proc/self/stat", "rb") as stat:  # after the ")" that ends the command name: field 3 on
                ticks = int(stat.read().rsplit(b")", 1)[1].split()[19])
            age = time.clock_gettime(time.CLOCK_BOOTTIME) - ticks / os.sysconf("SC_CLK_TCK")
        except (OSError, ValueError, IndexError, AttributeError):
            return None
        return cls(time.perf_counter() - max(age, 0.0), 0.0, "process start")

    def since(self) -> tuple[float, float]:
        """``(wall seconds, CPU seconds)`` from this moment to now."""
        return time.perf_counter() - self.wall, max(cpu_seconds() - self.cpu, 0.0)


@dataclass
class StageTimer:
    """Collects ``(stage, wall seconds)`` and each stage's CPU seconds in the order the stages ran.

    ``started`` is when the timer was made (``time.perf_counter()``; ``started_cpu``: :func:`cpu_seconds`
    then): a stage with a time budget measures it from there, and :meth:`close` records what no step did.

    >>> timer = StageTimer()
    >>> with timer.stage("work"):
    ...     pass
    >>> timer.freeze().stages[0][0]
    'work'
    """

    _stages: list[tuple[str, float]] = field(default_factory=list)
    _cpu: list[float | None] = field(default_factory=list)
    started: float = field(default_factory=time.perf_counter)
    started_cpu: float = field(default_factory=cpu_seconds)

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start, cpu = time.perf_counter(), cpu_seconds()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - start, cpu_seconds() - cpu)

    def add(self, name: str, seconds: float, cpu: float | None = None) -> None:
        """Record a time measured elsewhere (wall seconds, and CPU seconds when known)."""
        self._stages.append((name, float(seconds)))
        self._cpu.append(None if cpu is None else float(cpu))

    def elapsed(self) -> float:
        """Wall seconds since the timer was made."""
        return time.perf_counter() - self.started

    def close(self, name: str = "other") -> None:
        """Record the wall and CPU seconds since the timer was made that no step recorded yet, as ``name``:
        the steps then sum to the timer's whole time."""
        done = self.freeze()
        cpu = sum(c for c in done.cpu if c is not None)
        self.add(name, max(0.0, self.elapsed() - done.total_s), max(0.0, cpu_seconds() - self.started_cpu - cpu))

    def freeze(self) -> "Timings":
        return Timings(tuple(self._stages), tuple(self._cpu))


@dataclass(frozen=True)
class Timings:
    """Seconds per stage; a stage that ran twice appears twice. ``cpu``: per entry of ``stages`` its CPU
    seconds (user + system, see :func:`cpu_seconds`), None where not measured; empty: none measured."""

    stages: tuple[tuple[str, float], ...] = ()
    cpu: tuple[float | None, ...] = ()

    @property
    def total_s(self) -> float:
        return float(sum(s for _, s in self.stages))

    def seconds(self, name: str) -> float:
        """Total seconds spent in stages called ``name`` (0 if none)."""
        return float(sum(s for n, s in self.stages if n == name))

    def to_report(self) -> dict:
        """``{stage: wall seconds, ..., "total": ...}`` (stages that ran twice summed)."""
        out: dict[str, float] = {}
        for name, seconds in self.stages:
            out[name] = round(out.get(name, 0.0) + seconds, 4)
        out["total"] = round(self.total_s, 4)
        return out

    def cpu_report(self) -> dict:
        """``{stage: CPU seconds, ..., "total": ...}`` like :meth:`to_report`; None for a stage not measured.

        >>> Timings((("a", 2.0), ("b", 1.0)), (1.5, None)).cpu_report()
        {'a': 1.5, 'b': None, 'total': 1.5}
        """
        cpu = self.cpu or (None,) * len(self.stages)
        out: dict[str, float | None] = {}
        for (name, _), seconds in zip(self.stages, cpu):
            before = out.get(name, 0.0)
            out[name] = None if seconds is None or (name in out and before is None) else round(before + seconds, 4)
        out["total"] = round(sum(c for c in cpu if c is not None), 4)
        return out

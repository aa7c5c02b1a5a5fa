"""Progress of the SfM stages: a tqdm bar per stage on the terminal, or JSON-lines events.

pycolmap's calls run to the end without telling how far they are, so the pipeline cuts
the work into chunks (images for extraction, image pairs for matching) and reports
after each; mapping reports every registered image through pycolmap's callbacks.
"""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from typing import Iterator

from tqdm import tqdm

from ..events import EventWriter

STAGES = ("frames", "features", "matching", "mapping", "undistortion")


class Stage:
    """One running stage: `advance(n)` or `set(done)` moves its bar and sends events."""

    def __init__(self, reporter: "Reporter", name: str, total: int | None, unit: str):
        self.reporter, self.name, self.total, self.unit = reporter, name, total, unit
        self.done = 0
        self._last_event = 0.0
        self.bar = None
        if not reporter.quiet and not reporter.events.enabled:
            self.bar = tqdm(total=total, desc=f"sfm {name}", unit=unit, file=sys.stderr, dynamic_ncols=True, leave=True)

    def set(self, done: int, total: int | None = None) -> None:
        if total is not None and total != self.total:
            self.total = total
            if self.bar is not None:
                self.bar.total = total
        step, self.done = done - self.done, done
        if self.bar is not None and step:
            self.bar.update(step)
        now = time.monotonic()
        if now - self._last_event >= self.reporter.event_interval_s or (self.total is not None and done >= self.total):
            self._last_event = now
            self.reporter.events.emit("sfm_progress", stage=self.name, done=done, total=self.total, unit=self.unit)

    def advance(self, n: int = 1) -> None:
        self.set(self.done + n)

    def note(self, text: str) -> None:
        """A short status after the counts (e.g. the number of models)."""
        if self.bar is not None:
            self.bar.set_postfix_str(text)


class Reporter:
    """Makes the stages' bars (unless quiet) or events (when an event stream is on)."""

    def __init__(self, events: EventWriter | None = None, quiet: bool = False, event_interval_s: float = 0.5):
        self.events = events or EventWriter()
        self.quiet = quiet
        self.event_interval_s = event_interval_s
        self.stage_seconds: dict[str, float] = {}
        self.stages: tuple[str, ...] = STAGES  # this run's stages (no `frames` for photos)

    @contextmanager
    def stage(self, name: str, total: int | None, unit: str, detail: str = "") -> Iterator[Stage]:
        """Run one stage; its wall time lands in `stage_seconds[name]`."""
        self.events.emit("sfm_stage", stage=name, index=self.stages.index(name) + 1, n_stages=len(self.stages), total=total, unit=unit, detail=detail)
        start = time.perf_counter()
        stage = Stage(self, name, total, unit)
        try:
            yield stage
        finally:
            if stage.bar is not None:
                stage.bar.close()
            self.stage_seconds[name] = self.stage_seconds.get(name, 0.0) + time.perf_counter() - start

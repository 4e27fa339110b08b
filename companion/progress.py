"""Progress bars on a terminal for work over named stages (tqdm, on stderr).

A bar is drawn only when enabled (the commands enable it when stderr is a terminal, so pipes,
logs and CI stay quiet) and only once the work has lasted ``DELAY_S``: a short file shows
nothing. The .tlog reader has its own byte-level bar (``companion.recordings.tlog_reader``); this one
serves the importers (DataFlash, ULog, CSV), whose work comes in a few coarse stages.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from types import TracebackType
from typing import IO

#: seconds of work before a bar appears
DELAY_S = 1.0

#: what an importer calls as each stage ends (the stage's name), or None for no progress
StageCallback = Callable[[str], None] | None


class Stages:
    """``with Stages(enabled, "importing x.bin", total=4) as done: ...; done("indexed")``.

    ``done(name)`` marks one of ``total`` stages finished and shows its name beside the bar."""

    def __init__(self, enabled: bool, desc: str, total: int, *, file: IO[str] | None = None,
                 delay_s: float = DELAY_S) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="stage", leave=False, delay=delay_s,
                            file=file if file is not None else sys.stderr,
                            bar_format="{desc}: {n_fmt}/{total_fmt} stages|{bar}| {postfix} [{elapsed}]")

    def __call__(self, stage: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(stage, refresh=False)
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> Stages:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

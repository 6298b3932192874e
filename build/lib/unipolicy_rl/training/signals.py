"""Stopping a run cleanly: a signal ends it at an epoch boundary, where a checkpoint resumes exactly."""

from __future__ import annotations

import signal


class StopAtEpochEnd:
    """Ctrl-C or SIGTERM (``kill``, a scheduler's pre-emption) asks the loop to stop after the
    epoch in progress, so the checkpoint it then writes holds whole epochs and resumes exactly.
    A second signal stops at once (keeping the last periodic checkpoint)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested = False
        self._previous = {}

    def __enter__(self) -> StopAtEpochEnd:
        self._previous = {number: signal.signal(number, self._request) for number in self.SIGNALS}
        return self

    def __exit__(self, *exc_info) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)

    def _request(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print(f"\n{signal.Signals(signum).name}: stopping after this epoch (again to stop now)", flush=True)

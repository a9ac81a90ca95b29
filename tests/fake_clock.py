"""A clock that moves only when a test moves it, for the `clock` parameters of the fan-out and the pipeline
(roadgrip/cloud/pipeline/fanout.py, pipeline.py): a test advances it instead of sleeping, so its timing assertions hold
on any machine and cost no wall-clock time."""

from __future__ import annotations


class FakeClock:
    """callable() -> seconds, like time.monotonic or time.time; starts at `start_s`."""

    def __init__(self, start_s: float = 1_000.0):
        self.now_s = float(start_s)

    def __call__(self) -> float:
        return self.now_s

    def advance(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError(f"a clock does not go back: advance({seconds})")
        self.now_s += seconds

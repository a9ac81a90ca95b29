"""The processes a local cluster (roadgrip/cloud/cluster/local.py) starts itself: a `roadgrip` command in a session of
its own (`Child`), stopping several together with one deadline (`stop_children`), and when one that exited is
started again (`Restarts`: the backoff and the limit of local.py's supervision). Finding and ending whatever is left
of a cluster is roadgrip/cloud/cluster/reaper.py's."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

log = logging.getLogger(__name__)

KILLED_WAIT_S = 10.0  # a process killed with SIGKILL is waited for this long (longer: stuck in the kernel)
RESTART_FIRST_S = 1.0  # the first restart of a process that exited waits this long ...
RESTART_MAX_S = 30.0  # ... doubling with each restart of it, up to this
RESTART_LIMIT = 5  # restarts of one process; then it stays down


class Child:
    """A `roadgrip` command in a process of its own session, its output appended to `log_path`."""

    def __init__(self, name: str, args: list[str], log_path: Path, env: dict[str, str], url: str | None = None):
        self.name = name
        self.args = args
        self.log_path = log_path
        self.env = env
        self.url = url
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        with open(self.log_path, "ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "roadgrip", *self.args],
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=self.env,
                start_new_session=True,
            )

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    @property
    def returncode(self) -> int | None:
        """None while it runs (or before it started), else its exit status."""
        return None if self.proc is None else self.proc.poll()

    def log_tail(self, chars: int = 3000) -> str:
        return self.log_path.read_text(errors="replace")[-chars:] if self.log_path.exists() else ""

    def stop(self, grace_s: float) -> None:
        """SIGTERM, then SIGKILL to its process group after `grace_s`."""
        stop_children([self], grace_s)


def stop_children(children: list[Child], grace_s: float) -> None:
    """SIGTERM to each child, then SIGKILL to the process group of each that has not ended `grace_s` later (and to
    what is left in the group of each that has: a process of its own that it started)."""
    running = [c for c in children if c.proc is not None and c.proc.poll() is None]
    for child in running:
        child.proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for child in running:
        try:
            child.proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("%s (pid %d) did not stop within %.0f s: killed", child.name, child.proc.pid, grace_s)
    for child in children:
        if child.proc is None:
            continue
        try:
            os.killpg(child.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass  # the group is empty: nothing of it left
        try:
            child.proc.wait(KILLED_WAIT_S)
        except subprocess.TimeoutExpired:
            log.error("%s (pid %d) still there %.0f s after SIGKILL", child.name, child.proc.pid, KILLED_WAIT_S)


class Restarts:
    """When a process that exited is started again (module docstring, "Supervision")."""

    def __init__(self):
        self.count = 0  # restarts done
        self.due: float | None = None  # when the next one is (monotonic s), while the process is down

    def schedule(self, now: float) -> float | None:
        """The process was found down at `now`: the delay before its restart, None when it is not restarted."""
        if self.count >= RESTART_LIMIT:
            return None
        delay = min(RESTART_MAX_S, RESTART_FIRST_S * 2**self.count)
        self.due = now + delay
        return delay

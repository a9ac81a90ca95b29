"""Finding and ending every process of a local cluster (roadgrip/cloud/cluster/local.py), whoever started it and
whatever became of the process that ran the cluster.

Every process of a local cluster carries the variable TAG (its value: the cluster's data directory) in its
environment: the process that runs the cluster sets it in its own environment while the cluster runs, so that every
process it starts inherits it, and so do theirs (RabbitMQ's beam.smp, erl_child_setup and inet_gethost, epmd,
`roadgrip worker` and `roadgrip api`). `tagged` reads /proc/PID/environ, the environment a process was started with:
a process started by one of the cluster's is found even when the cluster never learned its pid (a fork cut short by
an interrupt, a daemonized server). PostgreSQL writes its processes' titles over that memory, so its postmaster, which
pg_ctl detaches, is found by its pid file instead (its backends end with it).

`python -m roadgrip.cloud.cluster.reaper DATA_DIR [PID_FILE ...]` is the cluster's reaper: started in a session of its own with a
pipe on its stdin whose writing end only the cluster's process holds, it waits for that pipe to close, which happens
when that process ends, however it ends (SIGKILL included), then ends every process tagged with DATA_DIR (`reap`)
and the processes named in the PID_FILEs, and exits. After a clean stop it finds nothing to end. Linux only (/proc).
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

TAG = "ROADGRIP_LOCAL_CLUSTER"
REAP_GRACE_S = 10.0  # SIGTERM, then SIGKILL to what is left after this long
POLL_S = 0.2


def tagged(value: str, exclude: frozenset[int] = frozenset()) -> set[int]:
    """The pids of the running processes whose environment has TAG=value (zombies, which have ended, left out)."""
    wanted = f"{TAG}={value}".encode()
    found = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) in exclude:
            continue
        try:
            if wanted not in (entry / "environ").read_bytes().split(b"\0"):
                continue
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue  # ended meanwhile, or not ours to read
        if state != "Z":
            found.add(int(entry.name))
    return found


def _signal(pids: set[int], signum: int) -> None:
    for pid in pids:
        try:
            os.kill(pid, signum)
        except (ProcessLookupError, PermissionError):
            pass


def _named(pid_files: tuple[Path, ...]) -> set[int]:
    """The running processes whose pids the files' first lines hold (a file absent: none)."""
    found = set()
    for path in pid_files:
        try:
            pid = int(path.read_text().split()[0])
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, ValueError, IndexError):
            continue
        if state != "Z":
            found.add(pid)
    return found


def reap(
    value: str, grace_s: float = REAP_GRACE_S, exclude: frozenset[int] = frozenset(), pid_files: tuple[Path, ...] = ()
) -> set[int]:
    """End every process tagged TAG=value or named in `pid_files`: SIGTERM (SIGQUIT to PostgreSQL's processes: its
    immediate shutdown; SIGTERM would wait for its clients), then SIGKILL to whatever is still there after
    `grace_s`, until none is left. Returns the pids found; `exclude`: pids to leave alone (the caller)."""
    exclude = exclude | {os.getpid()}

    def there() -> set[int]:
        return tagged(value, exclude) | (_named(pid_files) - exclude)

    found = there()
    for pid in found:
        _signal({pid}, signal.SIGQUIT if _is_postgres(pid) else signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while (left := there()) and time.monotonic() < deadline:
        found |= left
        time.sleep(POLL_S)
    while left:  # forks of the processes being killed are found and killed in turn
        found |= left
        _signal(left, signal.SIGKILL)
        time.sleep(POLL_S)
        left = there()
    return found


def _is_postgres(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip().startswith("postgres")
    except OSError:
        return False


def main() -> None:
    """Wait for stdin to close (the cluster's process has ended), then end what is left of the cluster."""
    value, pid_files = sys.argv[1], tuple(Path(arg) for arg in sys.argv[2:])
    while os.read(0, 4096):
        pass
    reap(value, pid_files=pid_files)


if __name__ == "__main__":
    main()

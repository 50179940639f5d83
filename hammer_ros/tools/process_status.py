"""Memory figures of a process from /proc (Linux), for the bench and the node memory probe."""

from __future__ import annotations

from pathlib import Path


def process_status_kib(field_name: str, pid: int | str = "self") -> int:
    """A memory figure (kiB) of a process from /proc/<pid>/status: VmRSS, VmHWM (its peak), ..."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field_name + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/{pid}/status has no {field_name}")


def child_pids(pid: int | str = "self") -> list[int]:
    """The pids of a process's children (/proc/<pid>/task/*/children; Linux)."""
    pids: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            pids += [int(child) for child in (task / "children").read_text().split()]
        except OSError:  # the thread ended meanwhile
            continue
    return pids

"""Memory and CPU figures of a process from /proc (Linux), for the bench, the node memory probe and
the rate probe."""

from __future__ import annotations

import os
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


def process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` so far, all its threads, not its children
    (Linux /proc; None where there is none, or once the process is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime (proc(5) fields 14, 15)


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants (children, their children, ...), parents first (Linux)."""
    tree, index = [pid], 0
    while index < len(tree):
        try:
            tree += child_pids(tree[index])
        except OSError:  # gone meanwhile
            pass
        index += 1
    return tree


def process_pss_kib(pid: int | str = "self") -> int:
    """The proportional set size (kiB) of a process (/proc/<pid>/smaps_rollup): its resident pages,
    each shared page counted as its share among the processes mapping it, so that a sum over
    processes counts a shared library once."""
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
        if line.startswith("Pss:"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/{pid}/smaps_rollup has no Pss")

"""Memory figures of a process from /proc (Linux), for the bench and the node memory probe."""

from __future__ import annotations

from pathlib import Path


def process_status_kib(field_name: str, pid: int | str = "self") -> int:
    """A memory figure (kiB) of a process from /proc/<pid>/status: VmRSS, VmHWM (its peak), ..."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field_name + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/{pid}/status has no {field_name}")

"""``hammer-ros reproduce``: the papers' numerical examples beside their published numbers.

Each target module (``cls``, ``plls``, ``bf``, ``semiparametric``, and ``real``: the measured
benchmark records in ``hammer_ros/data`` through ``diagnose``) exports
``rows(runs: int | None, seed: int) -> list[dict]`` with dicts holding the contract's keys
``paper, table, case, quantity, published, ours`` (published may be None where the paper
gives no number).
May import: numpy, scipy, ``hammer_ros.io`` (records), ``diagnosis``, ``identification``,
``errors``. Never rclpy, ``ros``, ``fleet``, ``cli`` or ``tools``.
"""

from __future__ import annotations

import importlib

__all__ = ["format_markdown", "reproduce_rows"]

def reproduce_rows(targets, runs: int | None = None, seed: int = 0) -> list[dict]:
    rows: list[dict] = []
    for target in targets:
        rows.extend(importlib.import_module(f"{__name__}.{target}").rows(runs, seed))
    return rows

def _cell(x) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.4f}"
    return str(x)

def format_markdown(rows: list[dict]) -> str:
    """One Markdown table per (paper, table)."""
    out: list[str] = []
    current = None
    for row in rows:
        key = (row["paper"], row["table"])
        if key != current:
            current = key
            out += ["", f"### {row['paper']} - {row['table']}", "",
                    "| case | quantity | published | ours |", "|---|---|---|---|"]
        out.append(f"| {row['case']} | {row['quantity']} | {_cell(row['published'])} | {_cell(row['ours'])} |")
    return "\n".join(out).strip() + "\n"

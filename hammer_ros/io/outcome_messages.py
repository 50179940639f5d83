"""The messages of one solve, as the node publishes them and replay writes them (one sequence for both)."""

from __future__ import annotations

from collections.abc import Callable

from ..messages.outputs import diagnostics_message, result_messages, stale_model_message
from ..streaming.config import EngineStats
from ..streaming.engine import SolveOutcome

DIAGNOSTICS = ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")


def outcome_messages(outcome: SolveOutcome, last_good: SolveOutcome | None, stats: EngineStats, stamp_ns: int, *,
                     frame_id: str, status_name: str,
                     complete_status: Callable[[dict], None] | None = None) -> list[tuple[str, str, dict]]:
    """(topic, type, values) of a solve: its results (``result_messages``); after a solve without a
    model, ``last_good`` (the last solve with one) again, marked stale; last the ``/diagnostics``
    array of ``status_name``, whose status ``complete_status`` extends with the caller's own values."""
    messages = result_messages(outcome, stamp_ns, frame_id)
    if not outcome.ok and last_good is not None:
        messages.append(stale_model_message(last_good, outcome))
    diagnostics = diagnostics_message(stats, outcome, stamp_ns, status_name)
    if complete_status is not None:
        complete_status(diagnostics["status"][0])
    messages.append((*DIAGNOSTICS, diagnostics))
    return messages

"""``hammer-ros diagnose DATA [--validation DATA2 | --split F] [--order N] [--reference COLUMN | /topic:field]
[--json] [--report FILE.html]``
(the subparser lives in ``hammer_ros.cli``; this is its thin adapter)."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from ..diagnosis.causes import EXTENSION, MEANING
from ..diagnosis.closed_loop import TEST_NAME as CLOSED_LOOP_TEST
from ..diagnosis.diagnose import Diagnosis, diagnose
from ..errors import IdentificationError, UsageError


def run(args: argparse.Namespace) -> int:
    if args.order is not None and args.order < 1:
        raise UsageError(f"--order: must be >= 1 (got {args.order})")
    if args.delay is not None and args.order is not None and args.delay > args.order:
        raise UsageError(f"--delay: relative degree {args.delay} exceeds --order {args.order}")
    from .. import api
    from .common import data_name, load_data

    record = load_data(args.data, args)
    validation = load_data(args.validation, args) if args.validation else None
    split, record_warnings = api.split_records(record, split=args.split, validation=validation)
    try:
        result = diagnose(split, args.order, args.delay)
    except (np.linalg.LinAlgError, FloatingPointError) as exc:
        raise IdentificationError(f"{data_name(args.data)}: no Hammerstein model can be fitted to this record "
                                  f"({exc})") from None
    if args.report:
        from ..diagnosis.report import write_report

        try:
            write_report(result, args.report, title=f"hammer-ros diagnose {' '.join(args.data)}")
        except OSError as exc:
            raise UsageError(f"--report: cannot write {args.report} ({exc.strerror or exc})") from None
        print(f"report written to {args.report}", file=sys.stderr)
    from .common import emit, format_warnings

    doc = api.Diagnosis(result, split, record_warnings).to_dict()
    emit(doc, args.json, "\n".join([summary(result.diagnosis), *format_warnings(doc["warnings"])]))
    return 0


def summary(d: Diagnosis) -> str:
    """The diagnosis in a few lines for a terminal."""
    b = d.baseline
    dead_time = d.baseline_model.get("dead_time", 0)
    lines = [f"baseline  {b.structure}: validation rms {b.rms:.4g}, fit {b.fit_percent:.1f} %"
             + (f", input dead time {dead_time} samples" if dead_time else ""),
             f"cause     {d.cause} (confidence {d.confidence:.2f}): {MEANING[d.cause]}"]
    if d.split_note:
        lines.insert(0, f"split     {d.split_note}")
    closed = [e for e in d.evidence if e.test == CLOSED_LOOP_TEST and e.note]
    if closed:
        lines.append(f"feedback  {'closed loop' if not closed[0].passed else 'no feedback found'}; {closed[0].note}")
    if d.coverage and d.coverage["judged_samples"] < d.coverage["validation_samples"]:
        lines.insert(1 if d.split_note else 0, f"coverage  {d.coverage['judged_on']}")
    if d.extended is not None:
        e = d.extended
        lines.append(f"extended  {d.steps[0].structure if d.steps else EXTENSION[d.cause]}")
        lines.append(f"          validation rms {e.rms:.4g}, fit {e.fit_percent:.1f} %, gain (rms ratio) {d.gain:.3f}")
        if len(d.steps) > 1:
            lines.append("chain     " + " -> ".join(f"{s.cause} (x{s.gain:.3f})" for s in d.steps))
        lines.append(f"          the chain stopped: {d.chain_stopped}")
    others = [f"{c} {g:.3f}" for c, g in d.candidates if c != d.cause]
    if others:
        lines.append(f"also fitted (gain): {', '.join(others)}")
    lines += [f"not fitted: {c}: {reason}" for c, reason in d.not_fitted]
    failed = [e for e in d.evidence if not e.passed]
    passed = len(d.evidence) - len(failed)
    lines.append(f"evidence  {passed} of {len(d.evidence)} tests passed" + (":" if failed else ""))
    lines += [f"  FAIL {e.test}: {e.value:.4g} > {e.bound:.4g}" for e in failed]
    return "\n".join(lines)

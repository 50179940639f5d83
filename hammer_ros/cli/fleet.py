"""``hammer-ros fleet BAGS... (--config YAML | --input /topic:field --output /topic:field) [identify
options] [--diagnose] [--scheduler ADDRESS | --workers N] [--out DIR] [--json]`` (the subparser lives
in ``hammer_ros.cli``; this is its thin adapter over ``hammer_ros.fleet``).

Every user mistake is found before any task runs: the options and config, the bags or the
manifest, the topics and fields (on the first bag that can be read), the output directory, the
settings of a resumed ``fleet.parquet`` and the scheduler. Exit 0 when every bag has a row (a bag
that fails is a row with its error), 130 after Ctrl-C (the finished rows are in fleet.parquet).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
from pathlib import Path

from ..errors import HammerRosError, UsageError

PARQUET, HTML, MCAP_DIR = "fleet.parquet", "fleet.html", "mcap"


def run(args: argparse.Namespace) -> int:
    from ..fleet.runner import FleetProgress, connect, run_fleet
    from ..fleet.table import read_rows, write_parquet
    from ..identification.methods import REFERENCE_METHODS
    from ..io.bag_config import config_channels, engine_config_from_params, load_msg_config, stream_spec, stream_specs
    from .replay import SignalStop, channel_runs, replay_settings

    if args.scheduler and args.workers is not None:
        raise UsageError("--scheduler and --workers: give one (--workers starts a local cluster)")
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers: must be >= 1 (got {args.workers})")
    if args.batch is not None and args.batch < 1:
        raise UsageError(f"--batch: must be >= 1 (got {args.batch})")
    if args.bags and args.manifest:
        raise UsageError("BAGS and --manifest: give one")
    params = load_msg_config(args.config) if args.config else {}
    source = str(args.config or "config")
    channels = config_channels(params, source)
    runs = channel_runs(args, channels, source) if len(channels) > 1 else []
    if runs:
        rates = {run.config.sample_rate for run in runs}
        if len(rates) > 1:
            raise UsageError(f"{source}: channels: fleet needs one sample_rate for all channels (got "
                             f"{', '.join(f'{run.name} {run.config.sample_rate:g}' for run in runs)})")
        excitation, response, config, solve_rate = runs[0].excitation, runs[0].response, runs[0].config, \
            runs[0].solve_rate
        reference = None
    else:
        if channels:  # one channel: exactly the fleet of its parameters
            params = channels[0].params
        excitation, response = stream_specs(args.input, args.output, params, source)
        reference = stream_spec("--reference", "reference", args.reference, params, source, required=False)
        engine_config_from_params(params, source)
        config, solve_rate = replay_settings(args, params, source)
        if reference is not None and config.method not in REFERENCE_METHODS:
            raise UsageError(f"--reference: not for {config.method} (instrumented methods: "
                             f"{', '.join(REFERENCE_METHODS)})")
    sources = _sources(args)
    for run in runs or [None]:
        _check_first_bag(sources, run.excitation if run else excitation, run.response if run else response,
                         reference)
    out_dir = Path(args.out or ".")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out: cannot create {out_dir} ({exc.strerror or exc})") from None
    if not os.access(out_dir, os.W_OK):
        raise UsageError(f"--out: {out_dir} is not writable")
    from ..fleet.tasks import FleetSettings

    settings = FleetSettings(excitation, response, config, solve_rate, str(params.get("frame_id", "")),
                             args.diagnose, str((out_dir / MCAP_DIR).resolve()) if args.out else None, reference,
                             tuple(runs))
    parquet = out_dir / PARQUET
    done_rows: list[dict] = []
    if args.resume and parquet.exists():
        try:
            done_rows, fingerprint = read_rows(parquet)
        except Exception as exc:  # pyarrow's errors: not a fleet.parquet of ours
            raise UsageError(f"--resume: {parquet}: not a fleet table ({type(exc).__name__}: {exc})") from None
        if fingerprint != settings.fingerprint():
            raise UsageError(f"--resume: {parquet} was made with other settings (run without --resume to redo it)")
        wanted = {s.path for s in sources}
        done_rows = [r for r in done_rows if r["path"] in wanted]
    client, cluster = connect(args.scheduler, args.workers if args.workers is not None else os.cpu_count() or 1)
    try:
        progress = FleetProgress(len(sources))
        with SignalStop(interrupt=True) as stop:  # SIGINT or SIGTERM: keep what finished, exit 128 + signal
            run = run_fleet(client, sources, settings, done_rows, progress=progress, batch=args.batch,
                            checkpoint=lambda rows: write_parquet(rows, parquet, settings.fingerprint(),
                                                                  config.sample_rate))
    finally:
        _close(client, cluster)
    if run.interrupted:
        print(f"hammer-ros: fleet interrupted: {run.bags} of {len(sources)} bags in {parquet}, {run.missing} "
              f"missing (run the same command with --resume to finish them)", file=sys.stderr)
        return 128 + (stop.signal or signal.SIGINT)
    return report(run.rows, sources, config.sample_rate, out_dir, args.json, run.wall_s, run.workers,
                  resumed=len({r["path"] for r in done_rows}))


def report(rows: list[dict], sources, sample_rate: float, out_dir: Path, as_json: bool, wall_s: float,
           workers: int, resumed: int = 0) -> int:
    """The change test on the rows (per group, and channel), fleet.html, and the summary (table or
    JSON) on stdout. With several channels: ``bags`` counts the bags, ``ok`` and ``failed`` the
    (bag, channel) rows, ``channels`` names them and each row and change has its ``channel``."""
    from ..fleet.changes import group_changes, relative_noise
    from ..fleet.report import change_line, write_report
    from ..fleet.table import bag_date, group_series, model_quantities

    order = {s.path: i for i, s in enumerate(sources)}
    rows = sorted(rows, key=lambda r: order.get(r["path"], len(order)))
    series = group_series(rows, sample_rate)
    noise = {q: relative_noise([s.values[q] for s in series]) for q in (series[0].values if series else {})}
    tests, changes = {}, []
    for s in series:
        tests[s.key], found = group_changes(s.key, s.times, s.values, noise, s.sds)
        changes += found
    by_group = {s.key: s for s in series}
    write_report(out_dir / HTML, series, tests, changes, rows, sample_rate)
    failed = [r for r in rows if r.get("error")]
    bags = len({r["path"] for r in rows})
    channels = list(dict.fromkeys(r["channel"] for r in rows if "channel" in r))
    if as_json:
        doc = {"bags": bags, "ok": len(rows) - len(failed), "failed": len(failed),
               **({"channels": channels} if channels else {}),
               "rows": [_json_row(r, model_quantities(r["model"], sample_rate) if r.get("model") else None)
                        for r in rows],
               "changes": [_json_change(c, by_group[c.group], bag_date) for c in changes],
               "parquet": str(out_dir / PARQUET), "html": str(out_dir / HTML), "wall_s": round(wall_s, 3),
               "workers": workers}
        json.dump(_finite(doc), sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
        return 0
    what = f"{bags} bags x {len(channels)} channels ({', '.join(channels)})" if channels else f"{bags} bags"
    print(f"fleet    {what}, {len(rows) - len(failed)} with a model, {len(failed)} failed"
          + (f" ({resumed} from the previous run)" if resumed else "")
          + f"; {wall_s:.1f} s on {workers} worker(s)")
    for r in failed:
        print(f"  failed {r['error']}")
    if changes:
        print(f"changed  {len(changes)} quantity change(s) in {len({c.group for c in changes})} of {len(series)} "
              "group(s) (robust CUSUM against each group's history):")
        for c in changes:
            print(f"  {change_line(c, by_group[c.group])}")
    else:
        print(f"changed  nothing: no quantity of the {len(series)} group(s) departs from its history")
    print(f"results  {out_dir / PARQUET}, {out_dir / HTML}")
    return 0


def _sources(args: argparse.Namespace):
    from ..fleet.sources import read_manifest, sources_from_paths

    if args.manifest:
        return read_manifest(args.manifest)
    if not args.bags:
        raise UsageError("BAGS: give bags (files, rosbag2 or other directories) or --manifest FILE")
    return sources_from_paths(args.bags)


def _check_first_bag(sources, excitation, response, reference=None) -> None:
    """The topics and fields on the first bag that can be read (a bag that cannot be read at all
    becomes an error row): a fleet whose bags lack them is a user mistake, found before any task."""
    from ..io.bag_index import bag_topics
    from ..io.replay import check_replay_input

    for source in sources:
        try:
            if not bag_topics(source.path):
                continue
        except HammerRosError:
            continue
        check_replay_input(source.path, excitation, response, reference=reference)
        return


def _close(client, cluster) -> None:
    try:
        client.close()
    finally:
        if cluster is not None:
            cluster.close()


def _json_row(row: dict, quantities: dict | None) -> dict:
    doc = {"path": row["path"], "group": row["group"], "labels": row["labels"], "start": row.get("start"),
           "end": row.get("end")}
    if "channel" in row:
        doc["channel"] = row["channel"]
    if row.get("error"):
        doc["error"] = row["error"]
        return doc
    doc.update(row["model"])
    doc["quantities"] = quantities
    if row.get("diagnosis") is not None:
        doc["diagnosis"] = row["diagnosis"]
    if row.get("out"):
        doc["out"] = row["out"]
    return doc


def _json_change(change, series, bag_date) -> dict:
    first = series.rows[change.first_index]
    flagged = series.rows[change.first_index:]
    return {"group": series.group, **({"channel": series.channel} if series.channel is not None else {}),
            "quantity": change.quantity, "first_bag": first["path"],
            "first_date": bag_date(first), "size": change.size, "size_percent": round(100 * change.size, 2),
            "bags": change.bags, "reference": change.reference, "latest": change.latest,
            "trend_per_day": change.trend_per_day, "flagged": [r["path"] for r in flagged]}


def _finite(value):
    """nan/inf as None (strict JSON)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value

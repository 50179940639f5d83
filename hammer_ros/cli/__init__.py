"""``hammer-ros``: the command-line contract of ../shared/spec/cli.md (a thin adapter).

Every user mistake ends in exit code 2 and one line on stderr naming the file, field or
option; results go to stdout (one JSON document with --json), logs/progress to stderr.
``identify`` is a layer over the Python API (``hammer_ros.api``); so is the record loading of ``identify``
and ``diagnose`` (``common.load_data`` = ``hammer_ros.read``). The subcommands ``diagnose``, ``replay`` and
``fleet`` are modules of this package; ``reproduce`` is ``hammer_ros.reproduce``; ``demo`` and ``bench`` are
tools of ``hammer_ros.tools``, the layer above, run by module name when the subcommand runs (never imported
here: ``bench`` imports this package to run ``replay`` as the command line does).
May import every layer except ``tools``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

import numpy as np

from ..errors import HammerRosError, IdentificationError
from .common import (
    OneLineErrorParser,
    add_data_options,
    add_identify_options,
    data_name,
    emit,
    format_model,
    load_data,
    options_from_args,
    positive_int,
    split_choice,
)

__all__ = ["build_parser", "main"]

REPRODUCE_TARGETS = ("cls", "plls", "bf", "semiparametric", "real")
# `all`: the papers' numerical examples; `real` (the measured records, minutes of diagnosis) runs on its own
REPRODUCE_ALL = ("cls", "plls", "bf", "semiparametric")



def cmd_identify(args: argparse.Namespace) -> int:
    from ..api import identify

    options = options_from_args(args)
    record = load_data(args.data, args)
    try:
        model = identify(record, method=args.method, refine=args.refine, **vars(options))
    except IdentificationError as exc:  # name the data the method could not identify from
        raise IdentificationError(f"{data_name(args.data)}: {exc}") from None
    doc = model.to_dict()
    emit(doc, args.json, format_model(doc))
    return 0



def cmd_reproduce(args: argparse.Namespace) -> int:
    from ..reproduce import format_markdown, reproduce_rows

    targets = REPRODUCE_ALL if args.target == "all" else (args.target,)
    rows = reproduce_rows(targets, runs=args.runs, seed=args.seed)
    emit({"rows": rows} if args.json else {}, args.json, None if args.json else format_markdown(rows))
    return 0



def _delegate(module: str, function: str = "run"):
    """The subcommand run by ``module.function(args)``, imported only when it runs."""
    def run(args: argparse.Namespace) -> int:
        return getattr(importlib.import_module(module), function)(args)

    return run



def build_parser() -> argparse.ArgumentParser:
    parser = OneLineErrorParser(prog="hammer-ros", description="Hammerstein system identification for ROS 2.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineErrorParser)
    sub.required = True

    p = sub.add_parser("identify", help="batch identification of a record")
    p.add_argument("data", metavar="DATA", nargs="+",
                   help="CSV, NPZ, .mcap or rosbag2 directory; several: separate runs of one experiment")
    add_data_options(p, reference=True)
    add_identify_options(p)
    p.add_argument("--refine", action="store_true",
                   help="refine the method's estimate on the simulation error (all its parts)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=cmd_identify)

    p = sub.add_parser("diagnose", help="what the model gets wrong, why, and the extended model")
    p.add_argument("data", metavar="DATA", nargs="+", help="record(s); several: separate runs")
    add_data_options(p, reference=True)
    p.add_argument("--validation", default=None, nargs="+", metavar="DATA2",
                   help="validation record(s) (default: --split; with several runs, the last whole runs)")
    p.add_argument("--split", type=split_choice, default=0.7, metavar="F|auto",
                   help="estimation fraction of DATA (default 0.7: validation on the last 30 %%), or auto: an "
                        "estimation part whose input range covers the validation part's, where the record allows")
    p.add_argument("--order", type=positive_int, default=None, help="order of the nominal linear block")
    p.add_argument("--delay", type=positive_int, default=None, help="relative degree (default: estimated)")
    p.add_argument("--report", default=None, metavar="FILE.html", help="write a self-contained HTML report")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_delegate("hammer_ros.cli.diagnose"))

    p = sub.add_parser("replay", help="feed a bag through the streaming engine")
    p.add_argument("bag", metavar="BAG")
    add_data_options(p, reference=True)
    add_identify_options(p)
    p.add_argument("--window", type=positive_int, default=None, help="window length W (samples)")
    p.add_argument("--sample-rate", type=float, default=None, help="sample grid rate in Hz (default: inferred)")
    p.add_argument("--solve-rate", type=float, default=None, help="solves per second of bag time")
    p.add_argument("--out", default=None, metavar="OUT.mcap", help="write every result into this MCAP (ROS 2 messages)")
    p.add_argument("--dashboard-out", default=None, metavar="DASH.mcap",
                   help="write the Foxglove dashboard channels (JSON with JSON schemas) into this MCAP")
    p.add_argument("--diagnose", action="store_true", help="also diagnose the final window (written as ~/diagnosis)")
    p.add_argument("--rate", type=float, default=None, help="play at this multiple of real time on the ROS graph")
    p.add_argument("--forgetting", type=float, default=None, help="exponential forgetting factor (default 1: window)")
    p.add_argument("--interpolation", choices=("zoh", "linear"), default=None, help="alignment (default zoh)")
    p.add_argument("--refine", action="store_true", help="refine every solve on the simulation error (as identify)")
    p.add_argument("--json", action="store_true")
    # None = take it from --config (then the engine default): the identify options' defaults
    p.set_defaults(func=_delegate("hammer_ros.cli.replay"), method=None, order=None, delay=None, poly=None)

    p = sub.add_parser("fleet", help="replay many bags (each channel of a --config with several) on Dask "
                       "distributed; what changed per group (and channel)")
    p.add_argument("bags", nargs="*", metavar="BAGS", help=".mcap files, rosbag2 directories, directories to search")
    p.add_argument("--manifest", default=None, metavar="FILE", help="CSV: a path column and label columns")
    add_data_options(p, reference=True)
    add_identify_options(p)
    for option, kind in (("--window", positive_int), ("--sample-rate", float), ("--solve-rate", float),
                         ("--forgetting", float)):
        p.add_argument(option, type=kind, default=None, help=f"as replay {option}")
    p.add_argument("--interpolation", choices=("zoh", "linear"), default=None, help="as replay --interpolation")
    p.add_argument("--refine", action="store_true", help="as replay --refine")
    p.add_argument("--diagnose", action="store_true", help="also diagnose each bag's final window")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS", help="an existing Dask scheduler (tcp://host:8786)")
    p.add_argument("--workers", type=int, default=None, help="processes of the local cluster (default: cores)")
    p.add_argument("--batch", type=int, default=None, metavar="N",
                   help="bags per Dask task (default: 1 for small fleets, up to 8 when each worker still gets 8 tasks)")
    p.add_argument("--out", default=None, metavar="DIR", help="fleet.parquet, fleet.html and each bag's results MCAP")
    p.add_argument("--resume", action="store_true", help="skip the bags already in DIR/fleet.parquet")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_delegate("hammer_ros.cli.fleet"), method=None, order=None, delay=None, poly=None)

    p = sub.add_parser("demo", help="simulated plant + live identification node")
    p.add_argument("--duration", type=float, default=60.0, help="seconds (default 60)")
    p.set_defaults(func=_delegate("hammer_ros.tools.demo"))

    p = sub.add_parser("reproduce", help="re-run the papers' examples beside their published numbers")
    p.add_argument("target", nargs="?", default="all", choices=(*REPRODUCE_TARGETS, "all"),
                   help="all = the papers' examples (about 40 s); real = the measured records (a few minutes)")
    p.add_argument("--runs", type=positive_int, default=None, help="Monte Carlo runs (default per table)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_reproduce)

    p = sub.add_parser("bench", help="speed and accuracy benchmark (not part of the tests)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--json", action="store_true")
    p.add_argument("--only", default=None, type=lambda text: [s.strip() for s in text.split(",") if s.strip()],
                   help="comma-separated sections: ingest,node,replay,solve,peers,memory,fleet (default all)")
    p.add_argument("--profile", action="store_true", help="print a cProfile of each section on stderr")
    p.set_defaults(func=_delegate("hammer_ros.tools.bench"))
    return parser



def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["node"]:
        from ..ros.node import main as node_main

        return node_main(argv[1:])
    try:
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except HammerRosError as exc:
        print(f"hammer-ros: error: {exc}", file=sys.stderr)
        return 2
    except np.linalg.LinAlgError as exc:  # a method's linear algebra failed on the user's data
        print(f"hammer-ros: error: {argv[0]}: numerical failure on this data ({exc})", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # stdout closed early (e.g. piped into head): not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # unreadable/unwritable file, disk full, ... (after BrokenPipeError, its subclass)
        print(f"hammer-ros: error: {exc.filename or argv[0]}: {exc.strerror or exc}", file=sys.stderr)
        return 2


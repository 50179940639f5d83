"""``hammer-ros``: the command-line contract of ../shared/spec/cli.md (a thin adapter).

Every user mistake ends in exit code 2 and one line on stderr naming the file, field or
option; results go to stdout (one JSON document with --json), logs/progress to stderr.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import sys
from pathlib import Path

import numpy as np

from .errors import HammerRosError, IdentificationError, UsageError
from .methods import METHODS, IdentifyOptions

REPRODUCE_TARGETS = ("cls", "plls", "bf", "semiparametric")


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error message (no usage dump) and exit code 2."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # values such as "--partition -0.25,0.25" start like a negative number, not an option
        # (the rule of Python >= 3.12's argparse)
        self._negative_number_matcher = re.compile(r"-\.?\d")

    def error(self, message: str) -> None:
        raise UsageError(message)


def _partition(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"--partition: not a comma-separated list of numbers: {text!r}") from None
    if not values or bool(np.any(np.diff(values) <= 0)):
        raise argparse.ArgumentTypeError(f"--partition: breakpoints must be strictly increasing: {text!r}")
    return values


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0: {text!r}")
    return value


def add_data_options(p: argparse.ArgumentParser) -> None:
    """Where the input/output signals are: CSV/NPZ column names or bag topic:field specs."""
    p.add_argument("--input", default=None, help="input column (CSV/NPZ, default u) or /topic:field.path (bag)")
    p.add_argument("--output", default=None, help="output column (CSV/NPZ, default y) or /topic:field.path (bag)")
    p.add_argument("--config", default=None, help="msg_config YAML mapping topics and fields (bags)")


def add_identify_options(p: argparse.ArgumentParser, default_method: str = "cls-markov") -> None:
    p.add_argument("--method", default=default_method, choices=list(METHODS), metavar="METHOD",
                   help=f"one of: {', '.join(METHODS)} (default {default_method})")
    p.add_argument("--order", type=_positive_int, default=3, help="order n of the linear block (default 3)")
    p.add_argument("--delay", type=_positive_int, default=1, help="relative degree d (default 1)")
    p.add_argument("--mu", type=_positive_int, default=None, help="number of Markov parameters (mu-Markov)")
    p.add_argument("--poly", type=_positive_int, default=3, help="polynomial order p of the nonlinearity (default 3)")
    p.add_argument("--partition", type=_partition, default=None,
                   help="breakpoints c1,c2,... of the piecewise-linear map (PLLS; for cls-arx/cls-markov: "
                   "a piecewise-linear F instead of the polynomial)")
    p.add_argument("--feedback-partition", type=_partition, default=None,
                   help="plls-hammerstein-feedback: breakpoints d1,d2,... of the output feedback map")
    p.add_argument("--tau-max", type=_positive_int, default=None, help="largest correlation lag (CLS)")
    p.add_argument("--harmonic", default=None, help="semiparametric: the single-harmonic record DATA2")


# option -> the methods that use it (given with any other method it would be silently ignored)
OPTION_METHODS = {
    "--mu": ("cls-markov", "nls-markov", "ls-markov"),
    "--partition": ("plls-hammerstein", "plls-feedback", "plls-hammerstein-feedback", "cls-arx", "cls-markov"),
    "--feedback-partition": ("plls-hammerstein-feedback",),
    "--harmonic": ("semiparametric",),
    "--tau-max": ("cls-arx", "cls-markov", "bf-hammerstein", "bf-feedforward"),
}


def check_option_conflicts(method: str, args: argparse.Namespace, streaming: bool = False) -> None:
    """A UsageError for an option given with a method that does not use it (contradictory
    options). ``streaming``: the engine always uses --tau-max for its correlation sums."""
    for option, methods in OPTION_METHODS.items():
        if getattr(args, option[2:].replace("-", "_"), None) is None or method in methods:
            continue
        if option == "--tau-max" and streaming:
            continue
        raise UsageError(f"{option}: not used by --method {method} (only by {', '.join(methods)})")


def options_from_args(args: argparse.Namespace) -> IdentifyOptions:
    check_option_conflicts(args.method, args)
    if args.order < 1:
        raise UsageError(f"--order: must be >= 1 (got {args.order})")
    if args.delay > args.order:
        raise UsageError(f"--delay: relative degree {args.delay} exceeds --order {args.order}")
    if args.mu is not None and args.mu < 1:
        raise UsageError(f"--mu: must be >= 1 (got {args.mu})")
    if args.poly < 1:
        raise UsageError(f"--poly: must be >= 1 (got {args.poly})")
    harmonic = None
    if getattr(args, "harmonic", None):
        rec = load_data(args.harmonic, args)
        harmonic = (rec.v, rec.y)
    elif args.method == "semiparametric":
        raise UsageError("--harmonic: the semiparametric method needs the single-harmonic record")
    return IdentifyOptions(
        order=args.order, delay=args.delay, mu=args.mu, poly=args.poly,
        partition=args.partition, tau_max=args.tau_max, harmonic=harmonic,
        feedback_partition=getattr(args, "feedback_partition", None),
    )


def is_bag(path: str) -> bool:
    p = Path(path)
    return p.suffix.lower() == ".mcap" or p.is_dir()


def load_data(path: str, args: argparse.Namespace):
    """The Record behind DATA: a CSV/NPZ file, or a bag with --input/--output or --config."""
    from .data_io import load_record

    if is_bag(path):
        from .bag_io import load_bag_record

        return load_bag_record(path, input_spec=args.input, output_spec=args.output, config=args.config)
    if getattr(args, "config", None):
        raise UsageError(f"--config: a msg_config maps bag topics, but {path} is a CSV/NPZ file (use --input/--output)")
    return load_record(path, args.input or "u", args.output or "y")


def emit(doc: dict, as_json: bool, text: str | None = None) -> None:
    if as_json:
        json.dump(doc, sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        sys.stdout.write((text if text is not None else json.dumps(doc, indent=2)) + "\n")


def cmd_identify(args: argparse.Namespace) -> int:
    from .methods import identify

    options = options_from_args(args)
    record = load_data(args.data, args)
    try:
        result = identify(args.method, record.v, record.y, options)
    except IdentificationError as exc:  # name the data the method could not identify from
        raise IdentificationError(f"{args.data}: {exc}") from None
    doc = result.to_json(record.v, record.y)
    emit(doc, args.json, format_model(doc))
    return 0


def format_model(doc: dict) -> str:
    """A short human-readable summary of an identify JSON document."""
    def roots(rs):
        return ", ".join(f"{re:.4f}{im:+.4f}j" if abs(im) > 1e-12 else f"{re:.4f}" for re, im in rs) or "-"

    lines = [f"method   {doc['method']} (order {doc['order']})", f"poles    {roots(doc['poles'])}",
             f"zeros    {roots(doc['zeros'])}"]
    if "gain" in doc:
        lines.append(f"gain     {doc['gain']:.4f}")
    if "nonlinearity" in doc:
        nl = doc["nonlinearity"]
        detail = nl.get("coefficients") or nl.get("breakpoints") or f"{len(nl.get('points', []))} points"
        lines.append(f"F(v)     {nl['kind']}: {detail}")
    if doc.get("fit_percent") is not None:
        lines.append(f"fit      {doc['fit_percent']:.2f} %   rms {doc['rms']:.4g}")
    return "\n".join(lines)


def cmd_reproduce(args: argparse.Namespace) -> int:
    from .reproduce import format_markdown, reproduce_rows

    targets = REPRODUCE_TARGETS if args.target == "all" else (args.target,)
    rows = reproduce_rows(targets, runs=args.runs, seed=args.seed)
    emit({"rows": rows} if args.json else {}, args.json, None if args.json else format_markdown(rows))
    return 0


def _delegate(module: str, function: str = "run"):
    def run(args: argparse.Namespace) -> int:
        return getattr(importlib.import_module(f"{__package__}.{module}"), function)(args)

    return run


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="hammer-ros", description="Hammerstein system identification for ROS 2.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    p = sub.add_parser("identify", help="batch identification of a record")
    p.add_argument("data", metavar="DATA", help="CSV, NPZ, .mcap or rosbag2 directory")
    add_data_options(p)
    add_identify_options(p)
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=cmd_identify)

    p = sub.add_parser("diagnose", help="what the model gets wrong, why, and the extended model")
    p.add_argument("data", metavar="DATA")
    add_data_options(p)
    p.add_argument("--validation", default=None, metavar="DATA2", help="validation record (default: --split)")
    p.add_argument("--split", type=float, default=0.7, help="estimation fraction of DATA (default 0.7)")
    p.add_argument("--order", type=_positive_int, default=None, help="order of the nominal linear block")
    p.add_argument("--delay", type=_positive_int, default=None, help="relative degree (default: estimated)")
    p.add_argument("--report", default=None, metavar="FILE.html", help="write a self-contained HTML report")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_delegate("diagnosis.cli"))

    p = sub.add_parser("replay", help="feed a bag through the streaming engine")
    p.add_argument("bag", metavar="BAG")
    add_data_options(p)
    add_identify_options(p)
    p.add_argument("--window", type=_positive_int, default=None, help="window length W (samples)")
    p.add_argument("--sample-rate", type=float, default=None, help="sample grid rate in Hz (default: inferred)")
    p.add_argument("--solve-rate", type=float, default=None, help="solves per second of bag time")
    p.add_argument("--out", default=None, metavar="OUT.mcap", help="write every result into this MCAP")
    p.add_argument("--rate", type=float, default=None, help="play at this multiple of real time on the ROS graph")
    p.add_argument("--forgetting", type=float, default=None, help="exponential forgetting factor (default 1: window)")
    p.add_argument("--interpolation", choices=("zoh", "linear"), default=None, help="alignment (default zoh)")
    p.add_argument("--json", action="store_true")
    # None = take it from --config (then the engine default): the identify options' defaults
    p.set_defaults(func=_delegate("replay"), method=None, order=None, delay=None, poly=None)

    p = sub.add_parser("demo", help="simulated plant + live identification node")
    p.add_argument("--duration", type=float, default=60.0, help="seconds (default 60)")
    p.set_defaults(func=_delegate("demo"))

    p = sub.add_parser("reproduce", help="re-run the papers' examples beside their published numbers")
    p.add_argument("target", nargs="?", default="all", choices=(*REPRODUCE_TARGETS, "all"))
    p.add_argument("--runs", type=_positive_int, default=None, help="Monte Carlo runs (default per table)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_reproduce)

    p = sub.add_parser("bench", help="speed and accuracy benchmark (not part of the tests)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--json", action="store_true")
    p.add_argument("--only", default=None, type=lambda text: [s.strip() for s in text.split(",") if s.strip()],
                   help="comma-separated sections: ingest,node,replay,solve,peers,memory (default all)")
    p.add_argument("--profile", action="store_true", help="print a cProfile of each section on stderr")
    p.set_defaults(func=_delegate("bench"))
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["node"]:
        from .node import main as node_main

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


if __name__ == "__main__":
    sys.exit(main())

"""What the subcommands share: option parsers, the data loader, output, the model summary."""

from __future__ import annotations

import argparse
import json
import re
import sys

import numpy as np

from ..errors import UsageError
from ..identification.methods import METHODS, IdentifyOptions


class OneLineErrorParser(argparse.ArgumentParser):
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



def split_choice(text: str) -> float | str:
    """--split: the estimation fraction, or ``auto``."""
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a fraction between 0 and 1 or 'auto' (got {text!r})") from None


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0: {text!r}")
    return value



def add_data_options(p: argparse.ArgumentParser, reference: bool = False) -> None:
    """Where the input/output signals are: CSV/NPZ column names or bag topic:field specs
    (``reference``: also --reference, the closed loop's reference signal)."""
    p.add_argument("--input", default=None, help="input column (CSV/NPZ, default u) or /topic:field.path (bag)")
    p.add_argument("--output", default=None, help="output column (CSV/NPZ, default y) or /topic:field.path (bag)")
    p.add_argument("--config", default=None, help="msg_config YAML mapping topics and fields (bags)")
    if reference:
        p.add_argument("--reference", default=None, metavar="COLUMN_OR_TOPIC:FIELD",
                       help="closed loop: the external reference r (CSV/NPZ column or /topic:field.path), the "
                       "instrument of cls-arx, cls-markov and plls-hammerstein (diagnose: every model is fitted "
                       "and judged on the reference's part of the input)")



def add_identify_options(p: argparse.ArgumentParser, default_method: str = "cls-markov") -> None:
    p.add_argument("--method", default=default_method, choices=list(METHODS), metavar="METHOD",
                   help=f"one of: {', '.join(METHODS)} (default {default_method})")
    p.add_argument("--order", type=positive_int, default=3, help="order n of the linear block (default 3)")
    p.add_argument("--delay", type=positive_int, default=1, help="relative degree d (default 1)")
    p.add_argument("--mu", type=positive_int, default=None, help="number of Markov parameters (mu-Markov)")
    p.add_argument("--poly", type=positive_int, default=3, help="polynomial order p of the nonlinearity (default 3)")
    p.add_argument("--partition", type=_partition, default=None,
                   help="breakpoints c1,c2,... of the piecewise-linear map (PLLS; for cls-arx/cls-markov: "
                   "a piecewise-linear F instead of the polynomial)")
    p.add_argument("--feedback-partition", type=_partition, default=None,
                   help="plls-hammerstein-feedback: breakpoints d1,d2,... of the output feedback map")
    p.add_argument("--tau-max", type=positive_int, default=None, help="largest correlation lag (CLS)")
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


def load_data(paths: str | list[str], args: argparse.Namespace):
    """The Record behind DATA (``hammer_ros.read``): a CSV/NPZ file, or a bag with --input/--output or
    --config; several DATA are one record of runs (``io.records.concatenate_records``)."""
    from ..api import read

    return read(paths, input=args.input, output=args.output, config=getattr(args, "config", None),
                reference=getattr(args, "reference", None))


def data_name(paths: str | list[str]) -> str:
    """DATA in messages: the path, or 'A.csv (+7 more)'."""
    if isinstance(paths, str):
        return paths
    return paths[0] if len(paths) == 1 else f"{paths[0]} (+{len(paths) - 1} more)"



def emit(doc: dict, as_json: bool, text: str | None = None) -> None:
    if as_json:
        json.dump(doc, sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        sys.stdout.write((text if text is not None else json.dumps(doc, indent=2)) + "\n")



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
    lines += format_warnings(doc.get("warnings", ()))
    return "\n".join(lines)


def format_warnings(warnings) -> list[str]:
    """One line per warning of a JSON document: 'warning  CODE: message'."""
    return [f"warning  {w['code']}: {w['message']}" for w in warnings]

"""The Foxglove layout of a node's (or a replay's) dashboard channels, for *Layouts -> Import from
file...*: ``python -m hammer_ros.tools.foxglove_layout [--config FILE] [--node NAME] [-o OUT]``.

Without ``--config`` (or with a config of one channel) it is the shipped layout on
``/<node>/dashboard/...``; with a config of several ``channels`` (a node params file or a
msg_config), one tab per channel on ``/<node>/<channel>/dashboard/...``: what the live node's
Foxglove server serves and ``replay --dashboard-out`` records (``messages.dashboard.foxglove_layout``).
A bad file or channel list exits 2 with one line naming it.
"""

from __future__ import annotations

import json
import sys

from ..cli.common import OneLineErrorParser
from ..errors import UsageError
from ..io.bag_config import config_channels, load_msg_config
from ..messages.dashboard import SHIPPED_NODE, foxglove_layout


def main(argv: list[str] | None = None) -> int:
    parser = OneLineErrorParser(prog="python -m hammer_ros.tools.foxglove_layout", description=__doc__.split("\n")[0])
    parser.add_argument("--config", help="node params file or msg_config YAML (its channels)")
    parser.add_argument("--node", default=SHIPPED_NODE, help=f"node name of the topics (default {SHIPPED_NODE})")
    parser.add_argument("-o", "--out", help="write the layout here (default: standard output)")
    try:
        args = parser.parse_args(argv)
        channels = config_channels(load_msg_config(args.config), args.config) if args.config else []
        text = json.dumps(foxglove_layout(args.node, [c.name for c in channels]), indent=2) + "\n"
        if args.out:
            try:
                with open(args.out, "w") as out:
                    out.write(text)
            except OSError as exc:
                raise UsageError(f"--out {args.out}: {exc.strerror or exc}") from None
        else:
            sys.stdout.write(text)
    except UsageError as exc:
        print(f"foxglove_layout: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

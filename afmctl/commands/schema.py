"""``afmctl schema``: print the JSON schema of the configuration file."""
from __future__ import annotations

import argparse

#: a small, complete configuration (shown by `afmctl run --help` and `afmctl schema --help`;
#: tests/test_config.py checks that it validates)
EXAMPLE_TOML = """\
[scanner]
name = "stage1"
axes = ["x", "y", "z"]
[scanner.calibration.x]
nm_per_V = 80.0                 # linear calibration where no model file is given

[amplifier]
driver = "mdt693b"              # mdt693b | mdt694b | gcs | nv200 | can
port = "/dev/ttyUSB0"
slew_V_per_s = 2000.0
[amplifier.limits_V.x]
min_V = 0.0
max_V = 150.0

[loop]
rate_Hz = 250                   # the 115200-baud MDT link carries about 380 points/s

[compensation.x]
model = "models/x_pi.json"      # from `afmctl identify`, relative to this file

[safety]
ramp_V_per_s = 200.0
watchdog_s = 0.1
on_finish = "safe"              # ramp to safe_V at the end ("hold": leave the output)

[trajectory]
kind = "raster"                 # raster | moves | indentation | text | spiral | file | queue
width_nm = 5000.0
height_nm = 5000.0
lines = 64
line_rate_Hz = 2.0
"""

HELP = """\
Print the JSON schema of afmctl's TOML configuration (the file given to `afmctl run
--config`). Every table, key, unit and allowed range is in it; editors can use it for
completion and validation.

Example:
  afmctl schema > afmctl-config.schema.json
  afmctl schema --out afmctl-config.schema.json

Unknown keys are errors; errors name the field and the allowed range. A configuration
looks like this (more in examples/*.toml):

{example}"""


def _help() -> str:
    return HELP.format(example="\n".join("  " + line for line in EXAMPLE_TOML.splitlines()))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("schema", help="print the configuration's JSON schema",
                              description=_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", metavar="FILE", help="write the schema to FILE instead of stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from ..config import json_schema
    text = json.dumps(json_schema(), indent=2) + "\n"
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
    else:
        print(text, end="")
    return 0

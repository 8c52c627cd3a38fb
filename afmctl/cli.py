"""The ``afmctl`` command line.

Each verb lives in its own module ``afmctl.commands.<verb>`` that defines
``register(subparsers) -> None``; the parser it adds sets ``func=run(args) -> int``.
Command modules import their heavy dependencies inside ``run`` so that ``--help`` is fast.

Errors a user can act on (bad files, bad configuration, device errors) are printed as one
line ``afmctl: error: ...`` with exit status 2, never a traceback.
"""
from __future__ import annotations

import argparse
import faulthandler
import importlib
import logging
import signal
import sys
from collections.abc import Sequence

#: verbs in the order ``afmctl --help`` lists them
VERBS = ("demo", "run", "sim", "view", "router", "excite", "calibrate", "identify", "compensate", "learn", "model", "drift",
         "amp", "log",
         "report", "schema")

DESCRIPTION = """\
afmctl — feedforward compensation for AFM piezo scanners.

Piezo scanners do not go where they are told: hysteresis bends scan lines, creep keeps
the tip moving after it stops, thermal drift walks the image away. afmctl identifies
models of these effects from measured data, inverts them, and streams the voltages that
put the tip where you want it.

Start here:
  afmctl demo --out demo-out        simulated scanner, grating images with/without compensation
  afmctl identify --model pi --data DATA.csv --out MODEL.json
  afmctl compensate --model MODEL.json --target TARGET.csv --out VOLTS.csv

Units everywhere: V, nm, s, °C. Each command has its own --help.
A running afmctl that seems stuck prints every thread's stack on `kill -USR1 PID`.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="afmctl", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    from . import __version__
    parser.add_argument("--version", action="version", version=f"afmctl {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="verb", metavar="COMMAND")
    for verb in VERBS:
        importlib.import_module(f"afmctl.commands.{verb}").register(sub)
    return parser


def _user_errors() -> tuple[type[BaseException], ...]:
    from pydantic import ValidationError

    from .errors import AfmctlError
    from afmctl.compensators.base import ModelError
    from afmctl.drivers.errors import AmplifierError
    return (AfmctlError, ModelError, AmplifierError, ValidationError)


def _one_line(err: BaseException) -> str:
    from pydantic import ValidationError
    if isinstance(err, ValidationError):
        from afmctl.compensators.errortext import validation_error_line
        return validation_error_line(err)
    return " ".join(str(err).split("\n"))


def _stacks_on_sigusr1() -> None:
    """``kill -USR1 PID`` prints every thread's stack to stderr (a stuck process explains
    itself; the tests send it before they give up on a child)."""
    if hasattr(signal, "SIGUSR1") and sys.stderr is not None and hasattr(sys.stderr, "fileno"):
        try:
            faulthandler.register(signal.SIGUSR1, all_threads=True)
        except (ValueError, OSError, RuntimeError, AttributeError):   # no usable stderr fd (embedded)
            pass


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.verb is None:
        parser.print_help()
        return 0
    level = logging.WARNING if args.verbose == 0 else (logging.INFO if args.verbose == 1 else logging.DEBUG)
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    if argv is None:                    # a process of its own, not a call from Python
        _stacks_on_sigusr1()
    try:
        return int(args.func(args) or 0)
    except _user_errors() as err:
        print(f"afmctl: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("afmctl: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

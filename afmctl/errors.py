"""User-facing errors of the afmctl service and command line."""
from __future__ import annotations


class AfmctlError(Exception):
    """An error a user can act on: printed as one line by the CLI, exit status 2.

    The message names the file or field and the allowed range.
    """


def error_line(err: BaseException) -> str:
    """An exception as one line for status, events and logs: its message with every run of
    whitespace (newlines included) folded to one space, or its class name when empty."""
    return " ".join(str(err).split()) or type(err).__name__

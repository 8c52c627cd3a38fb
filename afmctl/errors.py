"""User-facing errors of the afmctl service and command line."""
from __future__ import annotations


class AfmctlError(Exception):
    """An error a user can act on: printed as one line by the CLI, exit status 2.

    The message names the file or field and the allowed range.
    """

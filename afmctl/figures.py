"""Writing matplotlib figures from the CLI: the headless backend, and a save that turns a
file that cannot be written into one clear error line naming the option."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from .errors import AfmctlError


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the headless Agg backend (imported on first use, not at import)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_figure(fig: Any, path: str | Path, option: str = "--plot", dpi: int = 110) -> None:
    """Write ``fig`` to ``path`` as PNG and close it; an unwritable path is an
    :class:`AfmctlError` naming ``option`` (the CLI prints it as one line, exit status 2)."""
    try:
        fig.savefig(path, dpi=dpi)
    except OSError as err:
        raise AfmctlError(f"{option}: cannot write {path} ({err.strerror})") from None
    finally:
        pyplot().close(fig)

"""Opening a zenoh session from the ``[zenoh]`` settings (docs/ZENOH.md, *Connecting*)."""
from __future__ import annotations

from typing import Any

from ..errors import AfmctlError
from .settings import ZenohSettings


def open_session(settings: ZenohSettings, scanner_name: str | None = None) -> Any:
    """Open a zenoh session from :class:`ZenohSettings`; a failure is an :class:`AfmctlError`."""
    import zenoh
    config = settings.to_zenoh_config(scanner_name)
    try:
        return zenoh.open(config)
    except Exception as err:  # zenoh.ZError; e.g. the listen port is taken
        raise AfmctlError(f"zenoh: cannot open session ({' '.join(str(err).split())}); "
                          f"check zenoh.listen {settings.listen} / zenoh.connect {settings.connect}") from None

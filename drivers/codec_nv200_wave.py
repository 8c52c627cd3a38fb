"""Sans-I/O codec for the NV200 arbitrary waveform generator, as the vendor's ``nv200``
library (``WaveformGenerator``) drives it: ``gbarb,<i>,<percent>`` writes buffer slot i
(0..1023) with a percentage of the unit's voltage range (open loop: avmin..avmax),
``goarb``/``gsarb``/``gearb`` the start index and the loop's first and last index,
``gcarb`` the cycles (0 = until stopped), ``gtarb`` the sampling factor (a sample lasts
factor x 50 us), ``modsrc,3`` makes the generator the setpoint source, ``grun,1``/``grun,0``
run and stop it and ``grun`` reads 1 while it runs. Writes get no reply unless they fail.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

from .codec_common import format_inside
from .codec_nv200 import encode

BUFFER_SIZE = 1024
BASE_SAMPLE_S = 50e-6
MAX_FACTOR = 65535
PERCENT_DECIMALS = 5


def to_percent(value_V: float, dev_lo_V: float, dev_hi_V: float) -> float:
    """Voltage → percent of the unit's range ``dev_lo_V..dev_hi_V`` [V]."""
    return 100.0 * (value_V - dev_lo_V) / (dev_hi_V - dev_lo_V)


def encode_buffer(values_V: Sequence[float] | np.ndarray, dev_lo_V: float, dev_hi_V: float,
                  lo_V: float, hi_V: float) -> list[bytes]:
    """``gbarb,i,p`` for every sample; each percentage as sent decodes to a voltage inside
    ``[lo_V, hi_V]`` (the limits in force, within the unit's range)."""
    p_lo, p_hi = to_percent(lo_V, dev_lo_V, dev_hi_V), to_percent(hi_V, dev_lo_V, dev_hi_V)
    return [encode(f"gbarb,{i},{format_inside(to_percent(v, dev_lo_V, dev_hi_V), p_lo, p_hi, PERCENT_DECIMALS)}")
            for i, v in enumerate(values_V)]


def encode_start(n: int, factor: int, cycles: int) -> bytes:
    """Play slots 0..n-1, ``cycles`` times, a sample every ``factor`` x 50 us."""
    return b"".join(encode(c) for c in ("goarb,0", "gsarb,0", f"gearb,{n - 1}", f"gcarb,{cycles}",
                                        f"gtarb,{factor}", "modsrc,3", "grun,1"))


def encode_hand_back(value_V: float, lo_V: float, hi_V: float) -> bytes:
    """After the generator: the serial setpoint first takes the output's present value, then
    becomes the source again (``modsrc,0``) — so the output does not jump."""
    return encode("set," + format_inside(value_V, lo_V, hi_V, 3)) + encode("modsrc,0")

"""The MDT693B/MDT694B settings that are not channel voltages: display intensity, master
scan, the rotary knob, the friendly name and the command list, as the unit's serial commands
reach them (Thorlabs MDT693B/MDT694B manual, "Command list"; the ``mdt69x`` client library).

Commands (case-insensitive, answered in whichever prompt mode is active):

- ``INTENSITY?`` → ``15`` (bare integer); ``INTENSITY=n``, n = 0…15 (display brightness).
- ``MSENABLE?`` → ``0``/``1``; ``MSENABLE=0|1`` (master scan mode: the master scan voltage
  is added to every channel's voltage, each sum held inside that channel's limits).
- ``MSVOLTAGE?`` → ``[ 10.0]`` (bracketed like the voltage read-backs); ``MSVOLTAGE=v``
  clamped to 0…VLIMIT.
- ``ROTARYMODE?`` → ``0``; ``ROTARYMODE=n`` with n in :data:`ROTARY_MODES`.
- ``PUSHDISABLE?`` → ``0``/``1``; ``PUSHDISABLE=0|1`` (the knob's push-to-adjust; the Rust
  ``instruments`` crate spells it ``DISABLEPUSH``: both are accepted).
- ``FRIENDLY?`` → the name; ``FRIENDLY=name`` (printable, at most :data:`NAME_MAX` chars).
- ``?`` / ``HELP`` → the command list, one command per ``\\r``-separated line.

A set is answered by the prompt alone; a value out of range or of the wrong kind is not
defined (``CMD_NOT_DEFINED>``, the prompt alone in compatibility mode). The reply bodies
carry no ``>`` or ``*``: clients read a reply up to the prompt character.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

#: rotary knob modes the ``mdt69x`` client knows (0 default, 1 turn-pot, 2 fine) and the -1
#: (knob disabled) named by the ``instruments`` crate
ROTARY_MODES = (-1, 0, 1, 2)
INTENSITY_MAX = 15
NAME_MAX = 64

_INT = re.compile(rb"(INTENSITY|MSENABLE|ROTARYMODE|PUSHDISABLE|DISABLEPUSH)=\s*([+-]?\d+)\s*")
_MSV = re.compile(rb"MSVOLTAGE=\s*([+-]?(?:\d+(?:\.\d*)?|\.\d+))\s*")

HELP_LINES = (
    "?  or HELP - this list",
    "ID? - product information",
    "ECHO? / ECHO=0|1 - command echo",
    "VLIMIT? - output voltage range switch",
    "INTENSITY? / INTENSITY=0..15 - display brightness",
    "MSENABLE? / MSENABLE=0|1 - master scan mode",
    "MSVOLTAGE? / MSVOLTAGE=v - master scan voltage",
    "XVOLTAGE? / XVOLTAGE=v - x output voltage (also Y, Z)",
    "XYZVOLTAGE? / XYZVOLTAGE=x,y,z - all three outputs",
    "ALLVOLTAGE=v - every output",
    "XMIN? / XMIN=v, XMAX? / XMAX=v - x limits (also Y, Z)",
    "SYSMIN? / SYSMIN=v, SYSMAX? / SYSMAX=v - every channel's limits",
    "FRIENDLY? / FRIENDLY=name - friendly name",
    "SERIAL? - serial number",
    "CM? / CM=0|1 - MDT693A compatibility mode",
    "ROTARYMODE? / ROTARYMODE=n - rotary knob mode",
    "PUSHDISABLE? / PUSHDISABLE=0|1 - knob push-to-adjust",
    "RESTORE - restore the default limits",
)


@dataclass
class FrontPanel:
    """The panel and master-scan state. ``answer(cmd)`` returns ``(handled, body, ok)``:
    ``handled`` False when the command is not one of these; ``ok`` False for a bad value;
    ``body`` the reply text before the prompt (None for a set)."""

    name: str = "afmctl-sim"
    intensity: int = INTENSITY_MAX
    master_scan: bool = False
    master_V: float = 0.0
    rotary_mode: int = 0
    push_disabled: bool = False

    def master_offset_V(self) -> float:
        """What master scan adds to every channel now [V]."""
        return self.master_V if self.master_scan else 0.0

    def query(self, cmd: bytes) -> bytes | None:
        """The reply body of a panel query (upper-case ``cmd``), None if not one."""
        values = {b"INTENSITY?": str(self.intensity), b"MSENABLE?": str(int(self.master_scan)),
                  b"ROTARYMODE?": str(self.rotary_mode), b"PUSHDISABLE?": str(int(self.push_disabled)),
                  b"DISABLEPUSH?": str(int(self.push_disabled)), b"MSVOLTAGE?": f"[{self.master_V:5.1f}]",
                  b"?": "\r".join(HELP_LINES), b"HELP": "\r".join(HELP_LINES)}
        text = values.get(cmd)
        return None if text is None else text.encode()

    def set_int(self, cmd: bytes) -> bool | None:
        """An integer setting (upper-case ``cmd``): True set, False bad value, None not one."""
        m = _INT.fullmatch(cmd)
        if m is None:
            return None
        what, n = m.group(1), int(m.group(2))
        if what == b"INTENSITY" and 0 <= n <= INTENSITY_MAX:
            self.intensity = n
        elif what == b"MSENABLE" and n in (0, 1):
            self.master_scan = n == 1
        elif what == b"ROTARYMODE" and n in ROTARY_MODES:
            self.rotary_mode = n
        elif what in (b"PUSHDISABLE", b"DISABLEPUSH") and n in (0, 1):
            self.push_disabled = n == 1
        else:
            return False
        return True

    def master_voltage(self, cmd: bytes) -> float | None:
        """The value of a ``MSVOLTAGE=v`` command [V] (not yet clamped), None if not one."""
        m = _MSV.fullmatch(cmd)
        return float(m.group(1)) if m else None

    def set_name(self, raw_line: bytes) -> bool | None:
        """``FRIENDLY=name`` (the line as sent: the name keeps its case): True set, False a
        bad name, None not this command."""
        line = raw_line.strip()
        if not line.upper().startswith(b"FRIENDLY="):
            return None
        name = line[len(b"FRIENDLY="):].strip()
        if not 0 < len(name) <= NAME_MAX or not all(0x20 <= c < 0x7F and c not in b">*" for c in name):
            return False
        self.name = name.decode("ascii")
        return True

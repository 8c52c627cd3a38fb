"""One module per ``afmctl`` verb; see :mod:`afmctl.cli`."""

"""Demo and reports: ``afmctl demo``, the speed ladder, plots of run logs."""

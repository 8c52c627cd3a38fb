"""The simulated scanner: plant models, simulated amplifiers speaking the real protocols,
sample surfaces and AFM imaging. Imports :mod:`afmctl.compensators`, never :mod:`afmctl`."""

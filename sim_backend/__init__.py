"""The simulated scanner: plant models, simulated amplifiers speaking the real protocols,
sample surfaces and AFM imaging. Imports :mod:`compensators`, never :mod:`afmctl`."""

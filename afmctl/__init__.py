"""afmctl: feedforward hysteresis, creep and drift compensation for AFM piezo scanners.

The service package: configuration, trajectory sources, the real-time loop, safety, the
zenoh API, run logs, the command line and reports. Model math lives in
:mod:`afmctl.compensators`, amplifier links in :mod:`afmctl.drivers`, the simulated scanner in
:mod:`afmctl.sim_backend`.
"""
__version__ = "0.1.0"

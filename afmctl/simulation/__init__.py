"""Simulation wiring of the service: the simulated scanner as a service (``afmctl sim``) and
in-process simulation for ``afmctl run``."""

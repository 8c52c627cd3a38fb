"""Amplifier links: transports, sans-I/O protocol codecs, and the typed
:class:`drivers.base.Amplifier` interface on top.

Nothing here knows about trajectories or compensation, and nothing is imported eagerly.
"""

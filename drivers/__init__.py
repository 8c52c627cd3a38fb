"""Amplifier links: transports, sans-I/O protocol codecs, and the typed
:class:`drivers.base.Amplifier` interface on top.

* :func:`drivers.registry.open_amplifier` — open by name (``mdt693b``, ``mdt694b``,
  ``gcs``, ``nv200``, ``can``) and port (serial URL or ``INTERFACE:CHANNEL``);
* :mod:`drivers.base` (Amplifier, ConnectionState, VoltageLimits), :mod:`drivers.errors`;
* codecs: :mod:`drivers.codec_mdt`, :mod:`drivers.codec_gcs`, :mod:`drivers.codec_nv200`,
  :mod:`drivers.codec_can` (frames of ``afm_amplifier.dbc``);
* transports: :mod:`drivers.transport` (pyserial), :mod:`drivers.transport_can` (python-can).

Nothing here knows about trajectories or compensation, and nothing is imported eagerly.
See docs/DRIVERS.md.
"""

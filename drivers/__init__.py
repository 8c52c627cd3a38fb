"""Amplifier links: transports, sans-I/O protocol codecs, and the typed
:class:`afmctl.drivers.base.Amplifier` interface on top.

* :func:`afmctl.drivers.registry.open_amplifier` — open by name (``mdt693b``, ``mdt694b``,
  ``gcs``, ``nv200``, ``can``) and port (serial URL or ``INTERFACE:CHANNEL``);
* :mod:`afmctl.drivers.base` (Amplifier, ConnectionState, VoltageLimits), :mod:`afmctl.drivers.errors`;
* codecs: :mod:`afmctl.drivers.codec_mdt`, :mod:`afmctl.drivers.codec_gcs`, :mod:`afmctl.drivers.codec_nv200`,
  :mod:`afmctl.drivers.codec_can` (frames of ``afm_amplifier.dbc``);
* transports: :mod:`afmctl.drivers.transport` (pyserial), :mod:`afmctl.drivers.transport_can` (python-can).

Nothing here knows about trajectories or compensation, and nothing is imported eagerly.
See docs/DRIVERS.md.
"""

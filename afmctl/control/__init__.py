"""The controller and its outputs: the real-time loop's owner, its state machines (setpoints,
stream, wave), the compensation pipeline, safety, run logs and the amplifier it opens."""

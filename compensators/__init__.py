"""Pure numerics of afmctl: hysteresis, creep and drift operators, their inverses,
identification, and model files.

No I/O happens here besides reading and writing model JSON files
(:mod:`afmctl.compensators.models`). Nothing is imported eagerly: import the submodule you need.
"""

"""Defaults the ``afmctl learn`` parsers share, kept free of numpy so that building the
command line stays light (tests check them against the numerics' own constants)."""

#: the weighted central share of each raster line [%]: the part the error is judged on
#: (:data:`afmctl.compensators.learning_weights.REPORT_CENTRAL_PCT`) and an AFM images
CENTRAL_PCT = 80.0

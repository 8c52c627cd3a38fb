"""The Python API: what ``import afmctl`` offers a notebook (``afmctl.identify``,
``afmctl.compensate``, ...), arrays in and arrays out, units in every name. The command line
(afmctl/commands/) is a layer over these functions: printing, files and flags."""

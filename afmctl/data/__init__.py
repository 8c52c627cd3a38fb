"""Measured data of the offline workflow: CSV data files, identification data, excitation
signals, and scoring a model against measurements."""

"""Shared pytest fixtures. Test helpers that users may also want live in the packages
(e.g. ``sim_backend.testing``); this file only wires them into pytest."""
from __future__ import annotations

import os

# Headless plotting everywhere in the test suite.
os.environ.setdefault("MPLBACKEND", "Agg")

"""Zenoh bridge: a live m3pi endpoint standing in for a Vehicle FMU (not built yet; see the issues)."""

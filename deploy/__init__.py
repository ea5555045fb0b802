"""Zenoh configurations and the process graph of ``relaxmap run`` (data files)."""

"""Maths shared by several service cores (each core imports this, never another core)."""

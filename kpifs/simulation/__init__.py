"""Simulated scenes and injected companions."""

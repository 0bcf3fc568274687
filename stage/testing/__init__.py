"""Helpers for tests and benchmarks (dummy JACK servers, scripted bodies); never used by a show."""

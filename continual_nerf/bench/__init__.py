"""Benchmarks: commands that measure, never tests."""

"""Benchmarks (``make bench``): measured here, printed as a table; never asserted in unit tests."""

"""Shared builders of the tests, by topic: test modules import from here, never from each
other (tests/test_packaging.py checks it)."""

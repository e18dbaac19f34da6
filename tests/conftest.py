"""Shared test setup."""

import pytest


@pytest.fixture(autouse=True)
def _no_packed_chunks_from_earlier_tests():
    """Each test starts with an empty packed-chunk memo (it lives as long as the
    process): what a test counts of its wood's chunks must not depend on which
    tests ran before it."""
    from pipeline.optics import sources

    sources._PACKED.clear()
    yield

"""Fixtures of the estimator node tests (the harness itself is in rosharness.py)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from rosharness import Harness, closing_factory


@pytest.fixture
def harness(ros_context: Any) -> Iterator[Callable[..., Harness]]:
    """Factory: ``harness(params, reliable=True, namespace=None)``; closed after the test."""
    yield from closing_factory(functools.partial(Harness, ros_context))

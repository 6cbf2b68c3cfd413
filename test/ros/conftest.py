"""Fixtures of the estimator node tests (the harness itself is in rosharness.py)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest
from rosharness import Harness


@pytest.fixture
def harness(ros_context: Any) -> Iterator[Callable[..., Harness]]:
    """Factory: ``harness(params, reliable=True, namespace=None)``; closed after the test."""
    made: list[Harness] = []

    def make(params: dict[str, Any] | None = None, **kw: Any) -> Harness:
        h = Harness(ros_context, params, **kw)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()

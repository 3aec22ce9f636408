"""How many slots a summary lists one by one: the dry-run's, the plan's, the run's and
the review's summaries list at most :data:`LISTED` unfilled, missed or reviewed slots
and then only count the rest (the plan, report or log holds every one)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import TypeVar

T = TypeVar("T")

#: Slots a summary lists one by one before it only counts the rest.
LISTED = 10


def first(items: Iterable[T]) -> tuple[list[T], int]:
    """The first ``LISTED`` of ``items`` and how many more there are."""
    items = list(items)
    return items[:LISTED], max(len(items) - LISTED, 0)

"""One bounded queue with per-stream policy, used by every sender and receiver buffer.

Entries leave in arrival order. A **latest-wins** entry has a key (its stream): a newer
entry with the same key replaces an unsent one, which is returned to the caller (to be
counted as dropped), and the new one takes its place at the end. **Ordered** entries
are all kept, in a queue bounded by ``ordered_limit``. Memory is therefore bounded by the
number of keys plus ``ordered_limit``. No I/O and no clock here.
"""

from __future__ import annotations

from collections import deque
from typing import Generic, TypeVar

__all__ = ["StreamQueue"]

T = TypeVar("T")


class _Cell(Generic[T]):
    __slots__ = ("item", "key")

    def __init__(self, item: T | None, key: str | None) -> None:
        self.item = item
        self.key = key


class StreamQueue(Generic[T]):
    """Arrival-ordered queue of latest-wins slots and a bounded ordered queue.

    Args:
        ordered_limit: most ordered entries held at once.
    """

    def __init__(self, ordered_limit: int) -> None:
        self._cells: deque[_Cell[T]] = deque()
        self._latest: dict[str, _Cell[T]] = {}
        self.ordered_limit = ordered_limit
        self.ordered_count = 0

    def __len__(self) -> int:
        return self.ordered_count + len(self._latest)

    @property
    def ordered_full(self) -> bool:
        """True when :meth:`put_ordered` would refuse (without ``force``)."""
        return self.ordered_count >= self.ordered_limit

    def put_latest(self, key: str, item: T) -> T | None:
        """Put ``item`` in slot ``key``; return the unsent item it replaced, if any."""
        old = self._latest.get(key)
        replaced = None
        if old is not None:
            replaced, old.item = old.item, None
        cell = _Cell(item, key)
        self._latest[key] = cell
        self._cells.append(cell)
        return replaced

    def held(self, key: str) -> T | None:
        """The unsent item in slot ``key`` (the next :meth:`put_latest` of that key replaces
        it), or None."""
        cell = self._latest.get(key)
        return None if cell is None else cell.item

    def discard(self, key: str) -> T | None:
        """Remove the unsent item in slot ``key`` and return it (None when there is none)."""
        cell = self._latest.pop(key, None)
        if cell is None:
            return None
        item, cell.item = cell.item, None
        return item

    def put_ordered(self, item: T, *, force: bool = False) -> bool:
        """Append ``item`` to the ordered queue.

        Args:
            item: the entry.
            force: queue even when full (rare control messages such as a fatal error).

        Returns:
            False, with nothing queued, when the ordered queue is full.
        """
        if self.ordered_count >= self.ordered_limit and not force:
            return False
        self.ordered_count += 1
        self._cells.append(_Cell(item, None))
        return True

    def pop(self) -> T | None:
        """Remove and return the oldest entry, or None when empty."""
        cells = self._cells
        while cells:
            cell = cells.popleft()
            item = cell.item
            if item is None:
                continue  # replaced before it left
            if cell.key is None:
                self.ordered_count -= 1
            elif self._latest.get(cell.key) is cell:
                del self._latest[cell.key]
            return item
        return None

    def take(self) -> list[T]:
        """Remove and return every entry, in arrival order."""
        out = [c.item for c in self._cells if c.item is not None]
        self._cells.clear()
        self._latest.clear()
        self.ordered_count = 0
        return out

    def clear(self) -> None:
        """Drop everything."""
        self.take()

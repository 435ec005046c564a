"""The bus owner's timers (`BusOwner.after`): a heap under the bus lock.

Entries are [when, sequence number, callback, or None once removed or called]. Any thread adds
and removes (under the lock); only the owner pops, and its look at the first entry takes no
lock (`next_t`). A removed timer leaves the heap when the owner comes to it, or with the other
removed ones once they are most of the heap (a new list: the owner may be looking at the old
one), so a time-out whose future ended is not kept until it falls due.
"""

from __future__ import annotations

import heapq
import itertools
import threading
from typing import Any, Callable


class Timers:
    def __init__(self, lock: threading.Condition):
        self._lock = lock
        self._heap: list[list[Any]] = []
        self._seq = itertools.count()
        self._removed = 0            # removed entries still in the heap

    def __len__(self) -> int:
        return len(self._heap) - self._removed

    def add(self, when: float, callback: Callable[[], None]) -> Callable[[], None]:
        """(Under the lock) Returns what removes the timer, from any thread."""
        entry = [when, next(self._seq), callback]
        heapq.heappush(self._heap, entry)
        return lambda: self._remove(entry)

    def _remove(self, entry: list[Any]) -> None:
        with self._lock:
            if entry[2] is None:
                return
            entry[2] = None
            self._removed += 1
            if self._removed > 16 and 2 * self._removed > len(self._heap):
                heap = [e for e in self._heap if e[2] is not None]
                heapq.heapify(heap)
                self._heap, self._removed = heap, 0

    def next_t(self) -> float:
        """(Owner) When the next timer falls due (math.inf: none). Removed timers at the top
        of the heap leave it here."""
        heap = self._heap
        if heap and heap[0][2] is None:
            with self._lock:
                heap = self._heap
                while heap and heap[0][2] is None:
                    heapq.heappop(heap)
                    self._removed -= 1
        return heap[0][0] if heap else float('inf')

    def pop_due(self, now: float) -> list[Callable[[], None]]:
        """(Owner) The callbacks of the timers due at `now`, taken from the heap."""
        due = []
        with self._lock:
            heap = self._heap
            while heap and heap[0][0] <= now:
                entry = heapq.heappop(heap)
                if entry[2] is None:
                    self._removed -= 1
                else:
                    due.append(entry[2])
                    entry[2] = None           # called: removing it does nothing
        return due

    def take_all(self) -> list[Callable[[], None]]:
        """(Under the lock, at shutdown) Every waiting callback, in time order; none is left."""
        heap, self._heap, self._removed = sorted(self._heap), [], 0
        due = [e[2] for e in heap if e[2] is not None]
        for entry in heap:
            entry[2] = None
        return due

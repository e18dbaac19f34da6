"""A mapping of entries kept up to a number of bytes, the least recently used let go first
(the memory caches of woods' chunks, scans' tiles and TIFF slices)."""

from __future__ import annotations

import threading
from collections import OrderedDict


class ByteLRU:
    """A thread-safe mapping that drops its least recently used entries beyond
    ``limit`` bytes (keeping at least the newest); entries are never replaced."""

    def __init__(self, limit: int | None = None):
        self._limit = limit
        self.used = 0
        self._entries: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    @property
    def limit(self) -> int:
        return self._limit

    def get(self, key):
        """The entry ``key`` (now the most recently used), or None."""
        with self._lock:
            entry = self._entries.get(key)
            if entry is None:
                return None
            self._entries.move_to_end(key)
            return entry[0]

    def put(self, key, value, nbytes: int) -> None:
        """Add ``value`` of ``nbytes`` as ``key`` unless it is there already."""
        limit = self.limit
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                return
            self._entries[key] = (value, nbytes)
            self.used += nbytes
            while self.used > limit and len(self._entries) > 1:
                _, (_, size) = self._entries.popitem(last=False)
                self.used -= size

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self.used = 0

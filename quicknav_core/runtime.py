"""The process's state in one object that is passed down, never kept in a module.

A program builds one ``Runtime`` when it starts (the CLI for a command, a service worker, the API
process, a benchmark, a test session) and hands it to what it calls::

    runtime = Runtime(bank_folder=data / "room-banks", map_resolver=library.local_yaml)
    env, params = config.build("train", runtime)
    trainer = make_trainer(train_config, runtime)
    run_eval(eval_config, out_dir, runtime=runtime)

It holds

- ``bank_folder``: where built room banks are kept on disk (None: in memory only);
- ``map_resolver``: how ``map:<id>`` names of uploaded maps become local files (a service sets it);
- ``map_name``: the name a user gave an uploaded map (``map:<id>`` -> ``"depot"``, None if it has
  none or is gone), for pictures' titles (a service sets it);
- ``artifacts``: the artifact store of a service process (the library never reads it);
- caches: room banks (``banks``, bounded by bytes), compiled programs and what makes them
  shareable (``programs``) and warm trainers (``trainers``), both bounded by count; each value is
  built once per key even when threads ask for it at once.

A call given no runtime gets a fresh one: it computes the same results and shares nothing.
``quicknav_core`` keeps no module-level mutable state (``tests/test_layout.py`` checks it).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


class Cache:
    """A thread-safe LRU cache: ``get(key, make)`` builds a missing value once (other threads
    asking for the same key wait for it) and evicts the least recently used entries past
    ``max_items`` entries or ``max_bytes`` (``size(value)`` bytes each)."""

    def __init__(self, max_items: int, max_bytes: int | None = None,
                 size: Callable[[Any], int] | None = None):  # fmt: skip
        self.max_items = max_items
        self.max_bytes = max_bytes
        self._size = size or (lambda _: 0)
        self._items: OrderedDict[Hashable, Any] = OrderedDict()
        self._guard = threading.Lock()
        self._building: dict[Hashable, threading.Lock] = {}

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items

    def __getitem__(self, key: Hashable) -> Any:
        """The value kept for ``key`` (KeyError when none), not counted as a use."""
        with self._guard:
            return self._items[key]

    def get(self, key: Hashable, make: Callable[[], T]) -> T:
        with self._guard:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
            lock = self._building.setdefault(key, threading.Lock())
        with lock:
            with self._guard:
                if key in self._items:
                    return self._items[key]
            try:
                value = make()
            finally:
                with self._guard:
                    self._building.pop(key, None)
            with self._guard:
                self._items[key] = value
                self._evict()
            return value

    def clear(self) -> None:
        with self._guard:
            self._items.clear()

    def _evict(self) -> None:
        while len(self._items) > self.max_items:
            self._items.popitem(last=False)
        if self.max_bytes is None:
            return
        total = sum(self._size(v) for v in self._items.values())
        while len(self._items) > 1 and total > self.max_bytes:
            _, value = self._items.popitem(last=False)
            total -= self._size(value)


def _nbytes(value: Any) -> int:
    return int(getattr(value, "nbytes", 0))


@dataclass(eq=False)
class Runtime:
    """Room banks, the map resolver, compiled programs and the artifact store of one process."""

    bank_folder: Path | None = None
    map_resolver: Callable[[str], Path] | None = None
    map_name: Callable[[str], str | None] | None = None
    artifacts: Any = None
    max_programs: int = 64
    max_bank_bytes: int = 256 * 2**20
    max_trainers: int = 8
    programs: Cache = field(init=False, repr=False)
    banks: Cache = field(init=False, repr=False)
    trainers: Cache = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.bank_folder is not None:
            self.bank_folder = Path(self.bank_folder)
        self.programs = Cache(self.max_programs)
        # a bank larger than the budget is still kept while it is the only one
        self.banks = Cache(64, max_bytes=self.max_bank_bytes, size=_nbytes)
        # warm trainers (a service worker's, reused by jobs with the same config): each holds its
        # env's banks on the device and its compiled chunks, so only a few are kept
        self.trainers = Cache(self.max_trainers)

    def __deepcopy__(self, memo) -> Runtime:
        # process state is shared, never copied: a copy of an env (rejax deep-copies the envs it
        # is given) reads the same banks and compiled programs
        return self

    def program(self, key: Hashable, make: Callable[[], T]) -> T:
        """The compiled program (or shareable object) under ``key``, made once."""
        return self.programs.get(key, make)


def runtime_or_new(runtime: Runtime | None) -> Runtime:
    """``runtime``, or a fresh one for a caller that passed none (nothing is shared)."""
    return runtime if runtime is not None else Runtime()

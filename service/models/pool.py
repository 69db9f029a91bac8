"""At most N loaded networks of a gateway's models, loaded on first use, least recently used out.

`ModelPool` keeps what `load(name)` built for each model in use, up to `max_loaded` of them.
Whoever uses a model holds it (`use`, a context manager; a job holds its model for its whole
run): a held model is never evicted. A model that is not loaded and finds every slot held gets
`PoolFull`, which the gateway answers with a 503 and `Retry-After`. Loading and evicting happen
under one lock, the load itself outside it (a request for a loaded model never waits for
another's load), and two requests never load the same model twice; evicting calls `unload` and
forgets the object, and a later use loads it again (the checkpoint read again). The pool is the
only long-lived holder of what it loaded, so the objects alive are those `loaded` names plus any
a holder still uses: an evicted network is freed once its last user lets go.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Generic, TypeVar

T = TypeVar("T")


class PoolFull(RuntimeError):
    """Every slot holds a model in use: the one asked for cannot be loaded now."""

    def __init__(self, name: str, held: Sequence[str]) -> None:
        super().__init__(
            f"the model {name} is not loaded and every loaded one is in use "
            f"({', '.join(held)}); try again when a job ends"
        )
        self.name = name
        self.held = list(held)


class ModelPool(Generic[T]):
    """Loaded models by name, at most `max_loaded` (None: every model), least recently used
    evicted first among those nobody holds."""

    def __init__(
        self,
        names: Sequence[str],
        load: Callable[[str], T],
        *,
        max_loaded: int | None = None,
        unload: Callable[[T], None] | None = None,
    ) -> None:
        if max_loaded is not None and max_loaded < 1:
            raise ValueError(f"max_loaded must be at least 1, got {max_loaded}")
        self.names = list(names)
        self.max_loaded = max_loaded or len(self.names)
        self._load = load
        #: Called with each evicted object (settable, for an owner made after the pool).
        self.unload = unload
        self._loaded: OrderedDict[str, T] = OrderedDict()  # least recently used first
        self._holds: dict[str, int] = {}
        self._loading: dict[str, threading.Event] = {}
        self._lock = threading.Lock()
        #: How many times each model was loaded (a reload after eviction counts again).
        self.loads: dict[str, int] = dict.fromkeys(self.names, 0)

    def loaded(self) -> list[str]:
        """The models loaded now, least recently used first."""
        with self._lock:
            return list(self._loaded)

    def held(self) -> list[str]:
        """The models in use now."""
        with self._lock:
            return [name for name, count in self._holds.items() if count]

    @contextmanager
    def use(self, name: str) -> Iterator[T]:
        """The loaded model `name`, held until the block ends (loaded first where it is not,
        evicting the least recently used model nobody holds); `PoolFull` when every slot is held."""
        item = self.acquire(name)
        try:
            yield item
        finally:
            self.release(name)

    def release(self, name: str) -> None:
        """Let go of one hold of `name` (taken by `acquire`)."""
        with self._lock:
            self._holds[name] -= 1

    def free_slots(self) -> int:
        """Slots neither loaded nor being loaded: how many models a use loads now without
        evicting one."""
        with self._lock:
            return self.max_loaded - len(self._loaded) - len(self._loading)

    def items(self) -> list[tuple[str, T]]:
        """The loaded models and their objects, least recently used first."""
        with self._lock:
            return list(self._loaded.items())

    def acquire(self, name: str) -> T:
        """Hold `name`, loading it (outside the lock) when it is not loaded yet."""
        if name not in self.loads:
            raise KeyError(name)
        while True:
            with self._lock:
                if name in self._loaded:
                    self._loaded.move_to_end(name)
                    self._holds[name] = self._holds.get(name, 0) + 1
                    return self._loaded[name]
                loading = self._loading.get(name)
                if loading is None:
                    self._make_room(name)
                    loading = self._loading[name] = threading.Event()
                    self._holds[name] = self._holds.get(name, 0) + 1
                    break
            loading.wait()  # another request loads it: take it once it is there
        try:
            item = self._load(name)
        except BaseException:
            with self._lock:
                self._holds[name] -= 1
                del self._loading[name]
            loading.set()
            raise
        with self._lock:
            self._loaded[name] = item
            self.loads[name] += 1
            del self._loading[name]
        loading.set()
        return item

    def _make_room(self, name: str) -> None:
        """Evict least recently used unheld models until `name` fits (the lock is held); models
        being loaded take their slots already."""
        while len(self._loaded) + len(self._loading) >= self.max_loaded:
            victim = next((n for n in self._loaded if not self._holds.get(n)), None)
            if victim is None:
                raise PoolFull(name, [*self._loaded, *self._loading])
            item = self._loaded.pop(victim)
            if self.unload is not None:
                self.unload(item)

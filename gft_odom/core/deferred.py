"""A value computed once, when it is first asked for.

A scan's graph frequencies steer the default registration only through the map: a keyframe
remembers which of its points are smooth. The pose does not need them, so the pipeline hands
them over as a `Deferred` and computes them after the pose is published, as it does the map
rebuild. Whoever reads them first (the published cloud, the keyframe) pays for them; every
later reader gets the same array.
"""

from __future__ import annotations

import copy
import time
from typing import Any, Callable


class Deferred:
    """`compute()` run at the first `get()`; its result (or its exception, raised again at
    every `get()`) and the seconds it took kept."""

    def __init__(self, compute: Callable[[], Any]) -> None:
        self._compute: Callable[[], Any] | None = compute
        self._done = False
        self._value: Any = None
        self._error: Exception | None = None
        self.seconds = 0.0  # what the computation took (0 until it ran)

    @classmethod
    def of(cls, value: Any) -> 'Deferred':
        """A `Deferred` already holding `value` (for a reader that takes either kind)."""
        ready = cls(lambda: value)
        ready.get()
        return ready

    @property
    def done(self) -> bool:
        """Whether the value has been computed."""
        return self._done

    def get(self) -> Any:
        """The value, computed now if it was not yet."""
        if not self._done:
            if self._error is not None:
                raise self._error  # a failed computation is not run again
            t0 = time.perf_counter()
            try:
                self._value = self._compute()
            except Exception as exc:
                self._error = exc
                raise
            finally:
                self.seconds = time.perf_counter() - t0
            self._done = True
            self._compute = None  # what it held (a whole scan) can go
        return self._value

    def then(self, function: Callable[[Any], Any]) -> 'Deferred':
        """A `Deferred` of `function(value)`: nothing is computed before it is asked for."""
        return Deferred(lambda: function(self.get()))

    def __deepcopy__(self, memo: dict) -> 'Deferred':
        """A copy of the value once computed; before, the same computation (copying it
        would copy whatever it reads, e.g. a whole frequency source)."""
        if not self._done:
            return self
        twin = Deferred.of(copy.deepcopy(self._value, memo))
        twin.seconds = self.seconds
        return twin


def resolved(value: Any) -> Any:
    """`value.get()` for a `Deferred`, `value` itself otherwise."""
    return value.get() if isinstance(value, Deferred) else value

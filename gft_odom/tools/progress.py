"""Progress bars for long runs (tqdm), quiet when stderr is not a terminal unless forced."""

from __future__ import annotations

import sys
from contextlib import contextmanager


@contextmanager
def progress_bar(total: int | None, desc: str, unit: str = 'scan', enabled: bool | None = None):
    """Yield a callback `(done, total)` that advances a tqdm bar with ETA."""
    from tqdm import tqdm
    if enabled is None:
        enabled = True
    bar = tqdm(total=total, desc=desc, unit=unit, disable=not enabled, file=sys.stderr,
               dynamic_ncols=True, mininterval=0.5)
    state = {'done': 0}

    def update(done: int, new_total: int | None = None) -> None:
        if new_total is not None and new_total != bar.total:
            bar.total = new_total
        bar.update(done - state['done'])
        state['done'] = done

    try:
        yield update
    finally:
        bar.close()

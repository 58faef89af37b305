"""Progress bars for long runs (tqdm): off when stderr is not a terminal, log lines above them."""

from __future__ import annotations

import logging
import sys
from contextlib import ExitStack, contextmanager


@contextmanager
def progress_bar(total: int | None, desc: str, unit: str = 'scan', enabled: bool | None = None):
    """Yield a callback `(done, total)` that advances a tqdm bar with ETA.

    Shown only when stderr is a terminal (never into a log file or a pipe) and `enabled` is not
    False (`--quiet`). While it is shown, logging goes through tqdm, so log lines do not
    overwrite it.
    """
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm
    disable = enabled is False or not sys.stderr.isatty()
    bar = tqdm(total=total, desc=desc, unit=unit, disable=disable, file=sys.stderr,
               dynamic_ncols=True, mininterval=0.5)
    state = {'done': 0}

    def update(done: int, new_total: int | None = None) -> None:
        if new_total is not None and new_total != bar.total:
            bar.total = new_total
        bar.update(done - state['done'])
        state['done'] = done

    with ExitStack() as stack:
        if not bar.disable:
            stack.enter_context(logging_redirect_tqdm([logging.getLogger()]))
        try:
            yield update
        finally:
            bar.close()

"""Progress bars: none into a file or pipe; on a terminal, log lines are printed above them."""

from __future__ import annotations

import io
import logging

from gft_odom.tools import progress


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_no_bar_when_stderr_is_not_a_terminal(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr(progress.sys, 'stderr', err)
    with progress.progress_bar(10, 'replay') as update:
        update(5)
    assert err.getvalue() == ''


def test_on_a_terminal_logging_goes_through_the_bar(monkeypatch):
    err = FakeTerminal()
    monkeypatch.setattr(progress.sys, 'stderr', err)
    root = logging.getLogger()
    handler = logging.StreamHandler(err)
    root.addHandler(handler)
    try:
        with progress.progress_bar(10, 'replay') as update:
            update(3)
            # The redirect swapped our stream handler for tqdm's (tqdm.write above the bar).
            assert handler not in root.handlers
            logging.getLogger('gft_odom.test').warning('a line above the bar')
        assert handler in root.handlers
    finally:
        root.removeHandler(handler)
    text = err.getvalue()
    assert 'replay' in text and 'a line above the bar' in text
    with progress.progress_bar(10, 'quiet', enabled=False) as update:
        update(1)
    assert 'quiet' not in err.getvalue()


def test_only_the_progress_helper_imports_tqdm():
    """One helper for every long command: the core, the simulator and the commands hand it a
    callback; none of them draws a bar of its own."""
    import ast
    from pathlib import Path

    import gft_odom

    package = Path(gft_odom.__file__).parent
    importers = []
    for path in sorted(package.rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ''] if isinstance(node, ast.ImportFrom) else [])
            if any(name.split('.')[0] == 'tqdm' for name in names):
                importers.append(path.relative_to(package).as_posix())
    assert sorted(set(importers)) == ['tools/progress.py']

"""Every relative link of the README and the docs pages points at a file that is there."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LINK = re.compile(r'\]\(([^)\s]+)\)')


def _pages() -> list[tuple[Path, Path]]:
    """(page, folder its links are relative to)."""
    pages = [(REPO / 'README.md', REPO)]
    for page in sorted((REPO / 'docs').glob('*.md')):
        pages.append((page, page.parent))
    return pages


def test_relative_links_resolve():
    broken = []
    for page, base in _pages():
        for target in LINK.findall(page.read_text()):
            path = target.split('#')[0]
            if path and '://' not in path and not (base / path).exists():
                broken.append(f'{page.relative_to(REPO)}: {target}')
    assert not broken, '\n'.join(broken)


def test_the_readme_links_the_pages_the_long_material_moved_to():
    readme = (REPO / 'README.md').read_text()
    for page in ('ros_node', 'tools', 'parameters', 'facts', 'layout', 'benchmarks',
                 'registration'):
        assert f'](docs/{page}.md)' in readme, page


def test_the_readme_starts_with_the_two_commands():
    readme = (REPO / 'README.md').read_text()
    first_block = readme[readme.index('```bash'):]
    assert first_block.index('make demo') < first_block.index('make test') < 400

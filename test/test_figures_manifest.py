"""docs/figures.md lists every figure under docs/ with the command that draws it: every PNG and
GIF there is listed, and every file listed exists (a row marked as made later excepted)."""
import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
MANIFEST = REPO / 'docs' / 'figures.md'
NOT_YET_MADE = '(made with the shipped policy)'
ROW = re.compile(r'^\| `(docs/[^`]+\.(?:png|gif))` \|(.*)$', re.MULTILINE)


def listed() -> dict[str, str]:
    """Figure path -> the rest of its row."""
    return dict(ROW.findall(MANIFEST.read_text(encoding='utf-8')))


def test_every_figure_under_docs_is_in_the_manifest():
    on_disk = {path.relative_to(REPO).as_posix() for pattern in ('*.png', '*.gif')
               for path in (REPO / 'docs').rglob(pattern)}
    assert on_disk, 'no figure found under docs/'
    assert sorted(on_disk - listed().keys()) == []


def test_every_figure_the_manifest_lists_exists_or_is_marked_as_made_later():
    rows = listed()
    assert rows, 'no figure row found in docs/figures.md'
    missing = [path for path, rest in rows.items() if not (REPO / path).is_file() and NOT_YET_MADE not in rest]
    assert missing == []


def test_every_listed_figure_says_how_it_is_drawn():
    text = MANIFEST.read_text(encoding='utf-8')
    for path, rest in listed().items():
        section = text[:text.index(f'`{path}`')].rsplit('\n## ', 1)[-1]
        assert 'exit-decision ' in rest or 'exit-decision ' in section, f'{path}: no command'

"""One meaning of "the shipped policy": the default algorithm (``model.names.DEFAULT_ALGORITHM``).
The pages never put "the shipped policy" beside another policy's name, and every figure of
docs/figures.md names the policy its command draws it from ("the shipped policy" only for the
default one)."""
import re
from pathlib import Path

from exit_decision.model.names import DEFAULT_ALGORITHM, SHIPPED_ALGORITHMS

REPO = Path(__file__).resolve().parent.parent
MANIFEST = REPO / 'docs' / 'figures.md'
#: "the shipped policy", "the shipped options policy" (not "the shipped policies"), "the shipped `name`"
SHIPPED = re.compile(r'\bthe shipped (?:[\w-]+ ){0,2}policy\b(?![-\w])|\bthe shipped `(\w+)`', re.IGNORECASE)
FIGURE_ROW = re.compile(r'^\| `(docs/[^`]+\.(?:png|gif))` \| ([^|]*)\|?(.*)$')
COMMAND = re.compile(r'`(exit-decision [^`]+)`')


def policy_names() -> set[str]:
    """Every policy the pages may name: the shipped algorithms and every run under policies/."""
    return set(SHIPPED_ALGORITHMS) | {path.parent.name for path in (REPO / 'policies').rglob('policy.pt')}


def units(text: str) -> list[str]:
    """A page as sentences, table rows and lines of code blocks: what "next to" means."""
    found, paragraph, fenced = [], [], False
    for line in text.splitlines() + ['']:
        if line.lstrip().startswith('```'):
            fenced = not fenced
        elif fenced or line.startswith('|') or line.startswith('#'):
            found.append(line)
            continue
        if line.strip() and not line.lstrip().startswith('```'):
            paragraph.append(line.strip())
            continue
        found += re.split(r'(?<=[.;])\s+(?=[A-Z(`*\[-])', ' '.join(paragraph))
        paragraph = []
    return [unit for unit in found if unit]


def others_named(unit: str, names: set[str]) -> set[str]:
    """The policies other than the default one that ``unit`` names."""
    return (set(re.findall(r'[A-Za-z0-9_]+', unit)) & names) - {DEFAULT_ALGORITHM}


def shipped_conflicts(text: str, names: set[str]) -> list[str]:
    """The units that call a policy other than the default one "the shipped policy"."""
    return [unit for unit in units(text)
            if any(match[1] not in (None, DEFAULT_ALGORITHM) for match in SHIPPED.finditer(unit))
            or (SHIPPED.search(unit) and others_named(unit, names))]


def test_the_shipped_policy_is_never_beside_another_policys_name_in_the_pages():
    names = policy_names()
    assert DEFAULT_ALGORITHM in names and 'mdgqn_conditioned' in names
    problems = {page.relative_to(REPO).as_posix(): found for page in [REPO / 'README.md', *sorted((REPO / 'docs').glob('*.md'))]
                if (found := shipped_conflicts(page.read_text(encoding='utf-8'), names))}
    assert problems == {}


def test_the_check_finds_the_shipped_policy_beside_another_name():
    names = {DEFAULT_ALGORITHM, 'mdgqn_conditioned', 'gqn'}
    assert shipped_conflicts(f'Made by the shipped policy, `{DEFAULT_ALGORITHM}`. The grid: `gqn`.', names) == []
    assert shipped_conflicts('| `policies/mdgqn_conditioned/` (the shipped policy) | train |', names)
    assert shipped_conflicts('the first sweep (the shipped `mdgqn_conditioned` against `sumo`)', names)
    assert shipped_conflicts('The shipped options policy\nis `gqn` here.', names)
    assert shipped_conflicts('the shipped policies: `gqn` and `mdgqn_conditioned`', names) == []


def source_policy(command: str) -> str | None:
    """The policy a figure's command draws it from: its ``--policy`` run (a directory or its
    checkpoint), the default algorithm for ``stack`` without one; None for a command of many."""
    policies = re.findall(r'--policy (\S+)', command)
    if len(policies) > 1:
        return None
    if policies:
        path = Path(policies[0])
        return path.parent.name if path.suffix == '.pt' else path.name
    return DEFAULT_ALGORITHM if command.split()[1] == 'stack' else None


def figures() -> list[tuple[str, str, str | None]]:
    """docs/figures.md as (figure, its caption with its section's heading and lead, its source policy)."""
    rows = []
    for section in MANIFEST.read_text(encoding='utf-8').split('\n## ')[1:]:
        heading, _, body = section.partition('\n')
        lead = body.split('\n|', 1)[0]
        for line in body.splitlines():
            row = FIGURE_ROW.match(line)
            if row:
                sources = [source_policy(command) for command in COMMAND.findall(row[3]) or COMMAND.findall(lead)]
                rows.append((row[1], f'{heading} {lead} {row[2]}', next(filter(None, sources), None)))
    return rows


def test_every_figure_names_the_policy_its_command_draws_it_from():
    names = policy_names()
    listed = figures()
    assert {'docs/figures/training_reward.png', 'docs/figures/grid/test_reward.png'} <= {f for f, _, _ in listed}
    problems = []
    for figure, caption, source in listed:
        if source is None:
            continue
        named = set(re.findall(r'[A-Za-z0-9_]+', caption)) & names
        says_shipped = bool(SHIPPED.search(caption))
        if (source not in named and not (says_shipped and source == DEFAULT_ALGORITHM)) \
                or named - {source} or (says_shipped and source != DEFAULT_ALGORITHM):
            problems.append((figure, source, sorted(named), says_shipped))
    assert problems == []

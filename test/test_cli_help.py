"""What `exit-decision ... --help` says: every option and positional argument of every command
has a help string, with its default where it has one; no reStructuredText backticks; examples
that parse; and `exit-decision --version`. The parser is walked, not the pages (test_docs.py
holds docs/cli.md to it)."""
import argparse
import shlex
from pathlib import Path
from xml.etree import ElementTree

import pytest

from exit_decision.cli import build_parser
from exit_decision.cli.arguments import HelpFormatter, OldSpelling, shown_default

REPO = Path(__file__).resolve().parent.parent


def walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ('exit-decision',)):
    """(command path, its parser) for the top level and every command and subcommand under it."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from walk(child, (*path, name))


PARSERS = list(walk(build_parser()))


def arguments(parser: argparse.ArgumentParser):
    """The options and positional arguments a user gives (not -h/--help, --version, a command, nor
    an old spelling, hidden from --help: test_cli_arguments.py holds those)."""
    return [action for action in parser._actions
            if not isinstance(action, (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction,
                                       OldSpelling))]


def rendered_help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """The help text as --help prints it for ``action`` (before wrapping)."""
    formatter = parser._get_formatter()
    return formatter._expand_help(action) if action.help else ''


def name(path, action) -> str:
    return f'{" ".join(path)} {"/".join(action.option_strings) or action.dest}'


def test_the_walk_reaches_every_command_and_option():
    names = {' '.join(path) for path, _ in PARSERS}
    assert {'exit-decision stack', 'exit-decision train', 'exit-decision evaluate', 'exit-decision bag repair',
            'exit-decision fixture record', 'exit-decision bench'} <= names
    assert sum(len(arguments(parser)) for _, parser in PARSERS) > 100
    assert all(isinstance(parser.formatter_class, type) and issubclass(parser.formatter_class, HelpFormatter)
               for _, parser in PARSERS)


def test_every_option_and_positional_argument_has_help():
    missing = [name(path, action) for path, parser in PARSERS for action in arguments(parser)
               if not (action.help or '').strip() or action.help == argparse.SUPPRESS]
    assert not missing, 'arguments without a help string:\n' + '\n'.join(missing)


def test_every_command_has_help_in_its_parents_list():
    missing = [f'{" ".join(path)} {choice.dest}' for path, parser in PARSERS for action in parser._actions
               if isinstance(action, argparse._SubParsersAction)
               for choice in action._choices_actions if not (choice.help or '').strip()]
    assert not missing, 'commands without a help line:\n' + '\n'.join(missing)


def test_every_default_is_shown_or_said():
    """A default with a value (not None, not SUPPRESS) is in the help as --help prints it; a
    default of None or [] (a list option left empty) is said in words: "default: ...".
    Flags (store_true) and required arguments have no default to show."""
    problems = []
    for path, parser in PARSERS:
        for action in arguments(parser):
            if action.nargs == 0 or action.required or action.default is argparse.SUPPRESS:
                continue
            text = rendered_help(parser, action)
            if action.default is None or action.default == []:
                if 'default' not in text.lower():
                    problems.append(f'{name(path, action)}: default {action.default!r}, not said: {text!r}')
            elif shown_default(action.default) not in text:
                problems.append(f'{name(path, action)}: default {shown_default(action.default)!r} not shown: {text!r}')
    assert not problems, 'defaults --help does not give:\n' + '\n'.join(problems)


def test_a_default_is_said_once():
    """The formatter's "(default: ...)" is not added to a help that says its default itself."""
    problems = [f'{name(path, action)}: {text!r}' for path, parser in PARSERS for action in arguments(parser)
                for text in [rendered_help(parser, action)] if text.lower().count('default:') > 1]
    assert not problems, 'helps that give their default twice:\n' + '\n'.join(problems)


def test_no_help_text_has_a_backtick():
    problems = []
    for path, parser in PARSERS:
        texts = [parser.description, parser.epilog, parser.format_help()]
        texts += [rendered_help(parser, action) for action in parser._actions]
        texts += [choice.help for action in parser._actions if isinstance(action, argparse._SubParsersAction)
                  for choice in action._choices_actions]
        problems += [f'{" ".join(path)}: {text!r}' for text in texts if text and '`' in text]
    assert not problems, 'help text with backticks:\n' + '\n'.join(problems)


@pytest.mark.parametrize('command', [(), ('stack',), ('train',), ('evaluate',)], ids=lambda c: ' '.join(c) or 'top')
def test_examples_in_the_help_parse(command, tmp_path, monkeypatch):
    """The examples epilog of the top level, stack, train and evaluate: each `exit-decision ...`
    line parses (in a directory with the repository's config/ and policies/, and no bags/)."""
    parser = dict(PARSERS)[('exit-decision', *command)]
    lines = [line.strip() for line in (parser.epilog or '').splitlines() if line.strip().startswith('exit-decision ')]
    assert parser.epilog.startswith('examples:') and lines
    assert parser.format_help().rstrip().endswith(lines[-1])   # printed as written, one command a line
    for directory in ('config', 'policies'):
        (tmp_path / directory).symlink_to(REPO / directory)
    monkeypatch.chdir(tmp_path)
    for line in lines:
        args = build_parser().parse_args(shlex.split(line.replace('<time>', '20250101_000000'))[1:])
        assert callable(args.func), line


def test_version_prints_the_package_version_and_exits_0(capsys):
    version = ElementTree.parse(REPO / 'package.xml').getroot().findtext('version')
    with pytest.raises(SystemExit) as exit:
        build_parser().parse_args(['--version'])
    assert exit.value.code == 0
    assert capsys.readouterr().out.strip() == f'exit-decision {version}'
    assert f"version='{version}'" in (REPO / 'setup.py').read_text(encoding='utf-8')   # one version, two files

"""What every command shares: the parser (usage errors in one line), the argument types
(counts, seeds, existing paths, checkpoints, new paths), the config options, and the checks
of names against the config made before any work (``OptionError``)."""
from __future__ import annotations

import argparse
import math
import zipfile
from pathlib import Path

from exit_decision.config import ConfigError
from exit_decision.errors import UsageError


def shown_default(default) -> str:
    """A default as --help shows it: a path as typed, a list as its items, "" quoted."""
    if isinstance(default, (list, tuple)):
        return ' '.join(shown_default(item) for item in default)
    return '""' if default == '' else str(default)


def has_default(action: argparse.Action) -> bool:
    """Whether --help shows ``action``'s default by itself: an option or optional positional
    with a value (not None, not [], not a flag's False), whose help does not say it already."""
    return (action.default is not None and action.default is not argparse.SUPPRESS and action.default != []
            and action.nargs != 0 and not action.required and '%(default)' not in (action.help or ''))


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """argparse's help, descriptions and epilogs as written (the examples keep their lines), and
    every option's default after its help: "(default: 50)". A default that is None or [] is
    said in the help's own words ("default: ...")."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ''
        if text is argparse.SUPPRESS or not has_default(action):
            return text
        return text + ' (default: ' + shown_default(action.default).replace('%', '%%') + ')'


class Parser(argparse.ArgumentParser):
    """argparse's parser, its usage errors in one line (argument, value, what is allowed) and
    exit code 2; the usage is in --help, with the defaults (HelpFormatter; the subcommands'
    parsers are Parsers too)."""

    def __init__(self, *args, formatter_class=HelpFormatter, **kwargs):
        super().__init__(*args, formatter_class=formatter_class, **kwargs)

    def error(self, message: str):
        self.exit(2, f'{self.prog}: error: {message}\n')


def number(kind: type, low: float, inclusive: bool = True):
    """An argparse type: a finite ``kind`` number at or above ``low`` (above, if not ``inclusive``)."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not math.isfinite(value) or value < low or value == low and not inclusive:
            raise argparse.ArgumentTypeError(f'{text!r}: expected {"an integer" if kind is int else "a number"} '
                                             f'{">=" if inclusive else ">"} {low:g}')
        return value
    return parse


def existing(kind: str):
    """An argparse type: the path of an existing file (``kind`` 'file') or directory ('dir')."""
    def parse(text: str) -> Path:
        path = Path(text)
        if not (path.is_dir() if kind == 'dir' else path.is_file()):
            found = ' (a directory)' if kind == 'file' and path.is_dir() else ' (a file)' if path.exists() else ''
            raise argparse.ArgumentTypeError(f'{text!r}: no such {"directory" if kind == "dir" else "file"}{found}')
        return path
    return parse


def checkpoint(text: str) -> Path:
    """An argparse type: a checkpoint training wrote (policy.pt, last.pt), told from any other
    file by its format, torch.save's zip archive with a data.pkl, without loading torch (its
    content is checked when it is loaded)."""
    path = existing('file')(text)
    try:
        with zipfile.ZipFile(path) as archive:
            pickled = any(name.rpartition('/')[2] == 'data.pkl' for name in archive.namelist())
    except (zipfile.BadZipFile, OSError):
        pickled = False
    if not pickled:
        raise argparse.ArgumentTypeError(f'{text!r}: not a checkpoint (a policy.pt or last.pt written by training)')
    return path


def new_path(text: str) -> Path:
    """An argparse type: a path that does not exist yet (what is written there is never merged)."""
    if Path(text).exists():
        raise argparse.ArgumentTypeError(f'{text!r} exists already; allowed: a path that does not exist yet')
    return Path(text)


#: option types: counts, seeds and step numbers
COUNT, SEED, STEP = number(int, 1), number(int, 0), number(int, 0)


def config_options(parser: argparse.ArgumentParser) -> None:
    """The options that choose the config: its directory, a scenario override, overrides."""
    parser.add_argument('--config-dir', type=existing('dir'), default=None,
                        help='directory with scenario/graph/env/modes/reward YAML (default: config/)')
    parser.add_argument('--scenario-override', type=existing('file'), default=None,
                        help='YAML merged over scenario.yaml (a scenario variant; default: none, scenario.yaml '
                             'as it is)')
    parser.add_argument('--override', type=existing('file'), action='append', default=[],
                        help='YAML keyed by config file (env:, graph:, training:, ...) merged over the '
                             'config (repeatable; default: none)')


class OptionError(UsageError):
    """An option's value the config refuses (an unknown mode, method, variant, step), found
    before any work; reported in argparse's words: ``exit-decision <command>: error: argument
    <option>: ...``, exit code 2."""


def known(option: str, value, check) -> None:
    """Before any work: ``check(value)``, a lookup in the config that raises ConfigError for an
    unknown name, as an OptionError."""
    try:
        check(value)
    except ConfigError as error:
        raise OptionError(f'argument {option}: {error}') from None


def known_algorithm(algorithm: str, config, option: str = '--algorithm') -> None:
    """``option``: a learned method of the config, or <method>[_options][_conditioned] (OptionError)."""
    from exit_decision.model.names import method_of
    known(option, method_of(algorithm), config.training.method)


# --- one vocabulary: the old spellings of renamed options, and options given once per value ------

def note(namespace: argparse.Namespace, text: str) -> None:
    """A deprecation note for ``cli.main`` to print (once each) after the command, or to fold into
    the one line of a refusal."""
    notes = getattr(namespace, 'notes', None) or []
    if text not in notes:
        namespace.notes = [*notes, text]


class OldSpelling(argparse.Action):
    """An option's old spelling, hidden from --help; it still works, with a note."""


class Replaced(OldSpelling, argparse._StoreAction):
    """An old option with no one new spelling (``hint`` says what to give instead): stored as
    it was, for the command to take into the new option."""

    def __init__(self, option_strings, dest, hint: str = '', **kwargs):
        super().__init__(option_strings, dest, help=argparse.SUPPRESS, **kwargs)
        self.hint = hint

    def __call__(self, parser, namespace, values, option_string=None):
        super().__call__(parser, namespace, values, option_string)
        note(namespace, f'{option_string} is old: {self.hint}; the old spelling still works, for now')


class Renamed(OldSpelling):
    """An old spelling of an option, hidden from --help: its values go through the new option's
    action (its type, its repeats), and a note names the new spelling. ``several``: the old
    spelling took several values after it (``--runs a b``); each goes to the new one."""

    def __init__(self, option_strings, dest, new: argparse.Action, several: bool = False, **kwargs):
        super().__init__(option_strings, new.dest, nargs='+' if several else new.nargs, type=new.type,
                         choices=new.choices, default=argparse.SUPPRESS, help=argparse.SUPPRESS, metavar=new.metavar)
        self.new = new

    def __call__(self, parser, namespace, values, option_string=None):
        for value in values if self.nargs == '+' else [values]:
            self.new(parser, namespace, [value] if self.new.nargs == '+' else value, option_string)
        note(namespace, f'{option_string} is now {self.new.option_strings[-1]}; the old spelling still works, for now')


def renamed(parser: argparse.ArgumentParser, old: str, new: argparse.Action, several: bool = False) -> None:
    """Adds ``old``, an old spelling of the option ``new`` (what ``add_argument`` returned)."""
    parser.add_argument(old, action=Renamed, new=new, several=several)


class Repeated(argparse._AppendAction):
    """An option given once per value (``--only 1 --only 2``); the old form with several values
    after one option (``--only 1 2``) still works, with a note."""

    def __init__(self, option_strings, dest, **kwargs):
        kwargs['nargs'] = '+'
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        items = list(getattr(namespace, self.dest, None) or [])
        setattr(namespace, self.dest, items + list(values))
        if len(values) > 1:
            note(namespace, f'{option_string} takes one value; give it once per value: '
                            + ' '.join(f'{option_string} {value}' for value in values))


def shipped_policy_dir() -> Path:
    """The shipped policies/ (a checkout's, else the installed one)."""
    from exit_decision.model.names import default_policy_dir
    return default_policy_dir()


#: what a policy option allows, said by its refusals
POLICY_FORMS = ('a directory name under policies/ (e.g. mdgqn_options_conditioned), or the path of a policy '
                'directory or of its policy.pt')


def policy_directory(text: str) -> Path:
    """An argparse type: a policy chosen by its directory under policies/ or a path (a directory,
    or a file in it such as policy.pt): the directory."""
    path = Path(text)
    if not path.exists() and len(path.parts) == 1 and (shipped_policy_dir() / text).is_dir():
        path = shipped_policy_dir() / text
    if path.is_file():
        path = path.parent
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f'{text!r}: no such policy; allowed: {POLICY_FORMS}')
    return path


def policy(text: str) -> Path:
    """An argparse type: a policy chosen as ``policy_directory`` does, or a checkpoint file by
    its path: the checkpoint (the directory's policy.pt)."""
    path = Path(text)
    if not path.is_file():
        path = policy_directory(text) / 'policy.pt'
        if not path.is_file():
            raise argparse.ArgumentTypeError(f'{text!r}: no policy.pt in {path.parent}; allowed: {POLICY_FORMS}')
    try:
        return checkpoint(str(path))
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f'{text!r}: not a checkpoint (a policy.pt or last.pt written by '
                                         f'training); allowed: {POLICY_FORMS}') from None

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


def known_algorithm(algorithm: str, config) -> None:
    """--algorithm: a learned method of the config, or <method>[_options][_conditioned] (OptionError)."""
    from exit_decision.model.names import method_of
    known('--algorithm', method_of(algorithm), config.training.method)

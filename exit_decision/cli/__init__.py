"""The one command-line entry point: ``exit-decision <command> [options]``.

One module per command group (evaluation, training, stack, bags, experiments, results,
benchmarks), each adding its commands to the parser; this one builds it and reports a
refusal in one line.
"""
from __future__ import annotations

import argparse
import shlex
import sys

from exit_decision.cli import bags, benchmarks, evaluation, experiments, results, stack, training
from exit_decision.cli.arguments import OptionError, Parser
from exit_decision.config import ConfigError
from exit_decision.errors import PolicyError, StackError, UsageError

GROUPS = (evaluation, training, stack, bags, experiments, results, benchmarks)


#: exit-decision --help's first lines (plain text: argparse prints it as written)
DESCRIPTION = ('Graph RL highway-exit decisions for CAVs (SUMO + ROS 2): the project\'s jobs, one command each.\n'
               '"exit-decision <command> --help" gives a command\'s options and their defaults; docs/cli.md has '
               'them all.')

#: exit-decision --help's examples
EXAMPLES = '''examples:
  # the main job (scripts/main): the ROS 2 stack drives an episode, switches AGGP to CONP, records a bag
  exit-decision stack
  # that bag's episodes: a time-space diagram and a bird's-eye clip (its path is on the line stack prints after the metrics: bag: ...)
  exit-decision show bags/exit_decision_<time>
  # episodes without ROS and without a policy: the metrics table
  exit-decision run --episodes 3
  # the shipped policy against the neutral rule-based driver on 10 test seeds, under the validation modes
  exit-decision evaluate --policy policies/mdgqn_options_conditioned/policy.pt --driver rule_based --episodes 10
'''


def package_version() -> str:
    """The package's version: package.xml's where this code is a checkout (what runs is the
    checkout's), else the installed distribution's (pip or colcon), else "unknown"."""
    from pathlib import Path
    from xml.etree import ElementTree

    manifest = Path(__file__).resolve().parents[2] / 'package.xml'
    try:
        root = ElementTree.parse(manifest).getroot()
        if root.findtext('name') == 'exit_decision' and root.findtext('version'):
            return root.findtext('version').strip()
    except (OSError, ElementTree.ParseError):
        pass
    from importlib import metadata
    try:
        return metadata.version('exit_decision')
    except metadata.PackageNotFoundError:
        return 'unknown'


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog='exit-decision', description=DESCRIPTION, epilog=EXAMPLES)
    parser.add_argument('--version', action='version', version=f'%(prog)s {package_version()}',
                        help='print the version and exit')
    commands = parser.add_subparsers(dest='command', required=True, title='commands', metavar='<command>')
    for group in GROUPS:
        group.add_commands(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Runs the command; a refusal is one line and exit code 2 (a renamed option's note folded
    into it), else each note of an old spelling is a line on stderr after the command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.invocation = 'exit-decision ' + shlex.join(argv)   # what the outputs say made them
    notes = getattr(args, 'notes', None) or []
    folded = ''.join(f' (note: {text})' for text in notes)
    try:
        code = args.func(args)
    except OptionError as error:
        print(f'exit-decision {args.command}: error: {error}{folded}', file=sys.stderr)
        return 2
    except (ConfigError, PolicyError, UsageError) as error:
        print(f'exit-decision: {error}{folded}', file=sys.stderr)
        return 2
    except StackError as error:   # stack, fixture record: every node it started is stopped already
        print(f'exit-decision: {args.command}: {error}', file=sys.stderr)
        code = 1
    for text in notes:
        print(f'exit-decision {args.command}: note: {text}', file=sys.stderr)
    return code

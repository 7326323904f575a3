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


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog='exit-decision', description=__doc__.partition('\n')[0])
    commands = parser.add_subparsers(dest='command', required=True)
    for group in GROUPS:
        group.add_commands(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.invocation = 'exit-decision ' + shlex.join(argv)   # what the outputs say made them
    try:
        return args.func(args)
    except OptionError as error:
        print(f'exit-decision {args.command}: error: {error}', file=sys.stderr)
        return 2
    except (ConfigError, PolicyError, UsageError) as error:
        print(f'exit-decision: {error}', file=sys.stderr)
        return 2
    except StackError as error:   # stack, fixture record: every node it started is stopped already
        print(f'exit-decision: {args.command}: {error}', file=sys.stderr)
        return 1

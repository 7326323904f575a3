"""Commands on recorded bags: ``replay`` (the policy again on a bag's graphs), ``fixture record``
(the replay fixture the tests replay), ``bag repair`` and ``show`` (diagrams and clips)."""
from __future__ import annotations

import argparse
from pathlib import Path

from exit_decision.cli.arguments import config_options, existing, known, known_algorithm, number, policy
from exit_decision.config import load_project
from exit_decision.errors import UsageError


def cmd_replay(args: argparse.Namespace) -> int:
    """Re-run the decision policy on a bag's recorded graphs; compare with its commands."""
    from exit_decision.ros.bags.storage import BagError
    from exit_decision.model.names import default_policy_dir
    from exit_decision.ros.bags.replay import replay_decisions

    config = load_project(args.config_dir, args.scenario_override, args.override)
    if args.mode:
        known('--mode', args.mode, config.mode)
    if args.algorithm:
        known_algorithm(args.algorithm, config)
    try:
        report = replay_decisions(args.bag, config, args.policy_dir or default_policy_dir(), mode=args.mode,
                                  algorithm=args.algorithm, policy_file=args.policy, rebuild_graph=args.rebuild_graph)
    except BagError as error:
        raise UsageError(str(error)) from None
    print(report.summary())
    return 0


def cmd_fixture_record(args: argparse.Namespace) -> int:
    """Record the replay fixture again (after a policy, the shield or the graph changed on purpose)."""
    from datetime import datetime

    from exit_decision.ros.bags.replay import record_fixture

    print(record_fixture(args.out, Path('runs') / 'stack_logs' / f'fixture_{datetime.now():%Y%m%d_%H%M%S}'))
    return 0


def cmd_bag_repair(args: argparse.Namespace) -> int:
    """Make a bag whose recorder was killed readable up to its last complete chunk."""
    from exit_decision.ros.bags.repair import repair_bag
    from exit_decision.ros.bags.storage import BagError

    try:
        print(repair_bag(args.bag).summary())
    except BagError as error:
        raise UsageError(str(error)) from None
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    """Time-space diagrams and bird's-eye clips of a bag's episodes."""
    if not args.bag.exists():   # before loading ROS: the commonest mistake, answered fast
        raise UsageError(f'{args.bag}: no such bag (give the directory the recorder wrote)')
    from exit_decision.ros.bags.show import show_bag

    config = load_project(args.config_dir)
    for shown in show_bag(args.bag, config, args.out, episode=args.episode, start=args.start, end=args.end,
                          speed=args.speed, fps=args.fps):
        print(shown.summary())
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Adds ``replay``, ``fixture record``, ``bag repair`` and ``show``."""
    replay = commands.add_parser('replay', help='re-run the policy on a bag and compare with its commands')
    config_options(replay)
    replay.add_argument('bag', type=Path, help='a bag directory written by the recorder (exit-decision stack)')
    replay.add_argument('--mode', default=None, help='replay with this mode (default: the recorded one)')
    replay.add_argument('--algorithm', default=None,
                        help='replay with this learned method\'s policies in --policy-dir (default: the recorded one)')
    replay.add_argument('--policy', type=policy, default=None,
                        help='a policy to replay with instead: a directory name under policies/ or the path of a '
                             'policy directory or of a checkpoint (default: the policies of --algorithm in --policy-dir)')
    replay.add_argument('--policy-dir', type=existing('dir'), default=None,
                        help='directory of the policies, <algorithm>[_<mode>]/policy.pt (default: the shipped '
                             'policies/)')
    replay.add_argument('--rebuild-graph', action='store_true',
                        help='decide on graphs the graph builder makes again from the recorded states (a change '
                             'to the graph module shows too; a bag recorded without the graph topic needs it)')
    replay.set_defaults(func=cmd_replay)

    fixture = commands.add_parser('fixture', help='the replay fixture the tests replay (test/fixtures/replay_bag)')
    fixture_commands = fixture.add_subparsers(dest='fixture_command', required=True)
    record = fixture_commands.add_parser(
        'record', help='run the stack (shipped config and policy, a short episode with a mode switch), record it and '
                       'put it in place of the fixture once replay reproduces it')
    record.add_argument('--out', type=Path, default=Path('test/fixtures/replay_bag'),
                        help='fixture directory: bag/ and the override.yaml it was recorded with')
    record.set_defaults(func=cmd_fixture_record)

    bag = commands.add_parser('bag', help='bag maintenance')
    bag_commands = bag.add_subparsers(dest='bag_command', required=True)
    repair = bag_commands.add_parser('repair', help='make a bag whose recorder was killed (SIGKILL, power loss) '
                                                    'readable up to its last complete chunk; says what was lost')
    repair.add_argument('bag', type=Path, help='the bag directory the recorder wrote')
    repair.set_defaults(func=cmd_bag_repair)

    show = commands.add_parser('show', help='time-space diagrams (PNG) and bird\'s-eye clips (GIF; MP4 where ffmpeg '
                                            'exists) of the episodes of a bag')
    show.add_argument('bag', type=Path, help='a bag directory written by the recorder (exit-decision stack)')
    show.add_argument('--out', type=Path, default=None, help='output directory (default: <BAG>_show beside the bag)')
    show.add_argument('--config-dir', type=existing('dir'), default=None,
                      help='the config the bag was recorded with (the road; default: config/)')
    show.add_argument('--episode', type=number(int, 0), default=None, help='only this episode (default: every one)')
    show.add_argument('--start', type=number(float, 0), default=None,
                      help='[s] simulation time the window starts at (default: the episode\'s start)')
    show.add_argument('--end', type=number(float, 0), default=None,
                      help='[s] simulation time the window ends at (default: the episode\'s end)')
    show.add_argument('--speed', type=number(float, 0, inclusive=False), default=5.0,
                      help='clip speed, times real time')
    show.add_argument('--fps', type=number(float, 0, inclusive=False), default=10.0,
                      help='clip frames per second')
    show.set_defaults(func=cmd_show)

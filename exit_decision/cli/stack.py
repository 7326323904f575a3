"""The ``stack`` command: the whole ROS 2 stack in separate processes; and the options a run of
the nodes takes (real-time priority, the CPU split), ``bench ros``'s too."""
from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from exit_decision.config.seeds import TEST_SEED
from exit_decision.cli.arguments import (SEED, STEP, OptionError, Replaced, existing, known, known_algorithm, new_path,
                                         number, renamed)
from exit_decision.config import load_project
from exit_decision.errors import UsageError
from exit_decision.model.names import DEFAULT_ALGORITHM, SHIPPED_ALGORITHMS


def thread_priority_option(parser: argparse.ArgumentParser, what: str = '') -> None:
    """--thread-priority: the nodes' real-time priority (0: normal scheduling); ``what``: a help prefix."""
    from exit_decision.ros.stack.realtime import DESCRIPTION, PRIORITIES

    def priority(text: str) -> int:
        if not text.isdigit() or int(text) not in PRIORITIES:
            raise argparse.ArgumentTypeError(f'{text!r} is not allowed; allowed: an integer in '
                                             f'{PRIORITIES[0]}..{PRIORITIES[-1]}')
        return int(text)
    parser.add_argument('--thread-priority', type=priority, default=0, metavar=f'{PRIORITIES[0]}-{PRIORITIES[-1]}',
                        help=what + DESCRIPTION)


def cpu_split_option(parser: argparse.ArgumentParser, what: str = '') -> None:
    """--no-cpu-split: every node on every core; ``what``: a help prefix."""
    parser.add_argument('--no-cpu-split', action='store_true',
                        help=what + 'every node on every core, instead of the default with the normal scheduling: the '
                                    'decision path (bridge, graph builder, decision node) on the first half of the '
                                    'cores, the recorder and the visualizer on the rest')


def check_thread_priority(priority: int) -> None:
    """Before anything starts: a priority this user may not take is one line, not a node dying."""
    from exit_decision.ros.stack.realtime import refusal
    reason = refusal(priority) if priority else None
    if reason:
        raise UsageError(f'--thread-priority {reason}')


def stack_policy(reference: str | None, policy_dir: Path | None, modes=()) -> tuple[Path | None, str]:
    """(policy_dir, algorithm) the decision node takes for ``--policy``: a directory name under
    policies/ (or under the old ``--policy-dir``), the path of a policy directory or of its
    policy.pt (a directory named as its algorithm; one named ``<method>_<mode>``, a mode of
    ``modes``, is a per-mode policy: its method's, the other modes' beside it), or a per-mode
    method's name or path (``DIR/gqn``: the policies in DIR/gqn_<mode>/); ``None``: the shipped policy."""
    if reference is None:
        return policy_dir, DEFAULT_ALGORITHM
    path = policy_dir / reference if policy_dir else Path(reference)
    if path.is_file():
        path = path.parent
    if (path / 'policy.pt').is_file():
        method, _, mode = path.name.rpartition('_')
        return path.parent, method if method and mode in modes else path.name
    if len(Path(reference).parts) == 1:   # a name: of the shipped policies/ (or --policy-dir), or a per-mode method
        return policy_dir, reference
    if any(path.parent.glob(f'{path.name}_*/policy.pt')):   # a per-mode method's path
        return path.parent, path.name
    raise OptionError(f'argument --policy: {reference!r}: no policy.pt in {path}; allowed: a directory name under '
                      f'policies/, a per-mode method (its name, or DIR/<name> for its DIR/<name>_<mode>/ '
                      f'directories), or the path of a policy directory or of its policy.pt')


def check_policies(reference: str | None, policy_dir: Path | None, algorithm: str, modes: list[str]) -> None:
    """Before anything starts: a policy the decision node would load for ``modes`` and is not
    there is one line (a per-mode method needs one for each mode of the run; none ships)."""
    from exit_decision.model.names import default_policy_dir, is_conditioned, policy_path
    for mode in modes:
        path = policy_path(policy_dir or default_policy_dir(), algorithm, mode)
        if not path.is_file():
            each = '' if is_conditioned(algorithm) else \
                f'; {algorithm} needs one for each mode of the run ({", ".join(modes)})'
            raise OptionError(f'argument --policy: {reference!r}: no {path}{each}')


def cmd_stack(args: argparse.Namespace) -> int:
    """The whole ROS 2 stack in separate processes: an episode, a mode switch, a bag."""
    from datetime import datetime

    from exit_decision.evaluation import main_job
    from exit_decision.ros.stack.launcher import free_bag_path, run_stack

    config = load_project(args.config_dir)   # fail early, with the key, on a bad config
    check_thread_priority(args.thread_priority)
    matrix = config.mode_matrix
    args.policy_dir, args.algorithm = stack_policy(args.policy, args.policy_dir, config.modes)
    known_algorithm(args.algorithm, config, '--policy')
    mode = args.start_mode or matrix.aggressive.punished
    switch_to = matrix.conservative.punished if args.switch_to is None else args.switch_to or None
    known('--start-mode', mode, config.mode)
    if switch_to:
        known('--switch-to', switch_to, config.mode)
        if args.switch_at >= config.scenario.max_steps:
            raise OptionError(f'argument --switch-at: {args.switch_at}: expected a step below the scenario\'s '
                              f'max_steps ({config.scenario.max_steps}), or --switch-to "" for no switch')
    # another method than the shipped ones: the node loads its policies for the modes of this run only
    modes = [] if args.algorithm in SHIPPED_ALGORITHMS else [mode, *([switch_to] if switch_to else [])]
    check_policies(args.policy, args.policy_dir, args.algorithm, modes)
    stamp = f'{datetime.now():%Y%m%d_%H%M%S}'
    bag = args.bag or free_bag_path(Path('bags') / f'exit_decision_{stamp}')
    log_dir = Path('runs') / 'stack_logs' / stamp
    episodes = {0: 'episodes until stopped', 1: '1 episode'}.get(args.episodes, f'{args.episodes} episodes')
    switching = f', switching to {switch_to} at step {args.switch_at}' if switch_to else ''
    print(f'the stack: {args.algorithm} in {mode}{switching}, seed {args.seed}, {episodes}', flush=True)
    run = run_stack(mode=mode, modes=modes, algorithm=args.algorithm, episodes=args.episodes, seed=args.seed,
                    bag_path=bag, log_dir=log_dir,
                    switch_to=switch_to, switch_at_step=args.switch_at,
                    config_dir=str(args.config_dir or ''), policy_dir=str(args.policy_dir or ''),
                    visualizer=not args.no_visualizer, thread_priority=args.thread_priority,
                    cpu_split=not args.no_cpu_split, compression=args.compression,
                    say=lambda line: print(line, flush=True), step_length=config.scenario.step_length)
    print()
    if run.stopped_by:
        print(f'stopped by {run.stopped_by}: {len(run.episodes)} episode(s) finished; the nodes stopped')
    if run.episodes:
        label = f'{args.algorithm}, {mode}' + (f' -> {switch_to}' if run.mode_switch.endswith('accepted') else '')
        print('\n'.join(main_job.metrics_lines(run.episodes, config.scenario.emergency_braking_threshold, label)))
    else:
        print('no episode finished' + ('' if run.stopped_by else f' (see the nodes\' logs in {log_dir}/)'))
    if switch_to and not run.mode_switch:
        print(f'no mode switch: the first episode did not reach step {args.switch_at}')
    elif run.mode_switch and not run.mode_switch.endswith('accepted'):
        print(f'the mode switch was not made: {run.mode_switch}')
    elif run.mode_switch and run.episodes:   # what the switch changed, beside the same seed without it
        from exit_decision.model.names import default_policy_dir
        from exit_decision.ros.bags.switch import switch_outcome
        outcome = switch_outcome(bag, config, Path(args.policy_dir) if args.policy_dir else default_policy_dir(),
                                 args.algorithm, args.seed)
        if outcome is None:
            print(f'the bag\'s decisions keep one mode: the switch ({run.mode_switch}) did not land in it')
        else:
            timing = main_job.SwitchTiming(run.switch.asked, run.switch.requested, outcome.switch.step,
                                           config.env.decision_interval, config.scenario.step_length)
            print(main_job.timing_line(mode, switch_to, timing))
            print(main_job.returns_line(outcome))
            print(main_job.verdict_line(outcome))
            print(main_job.consistency_line(outcome))
    print(f'bag: {bag}')
    print('\n'.join(main_job.next_lines(bag, log_dir)))
    failed = {name: code for name, code in run.return_codes.items() if code not in (0, -2, -9)}
    if failed:
        print(f'nodes that failed: {failed}', file=sys.stderr)
        return 1
    if run.stopped_by:   # until stopped (--episodes 0): the end asked for; else the run was cut short
        return 0 if args.episodes == 0 else 128 + signal.Signals[run.stopped_by].value
    return 0 if run.episodes else 1


#: stack --help's examples
STACK_EXAMPLES = '''examples:
  # the main job (scripts/main): the shipped policy, AGGP switched to CONP at step 300, seed 10000, a bag in bags/
  exit-decision stack
  # another start mode, switch and seed, into a bag of a chosen name; then its diagrams and clip
  exit-decision stack --start-mode CONI --switch-to AGGI --switch-at 200 --seed 10001 --bag bags/coni_to_aggi
  exit-decision show bags/coni_to_aggi
  # no switch, no visualizer, episodes until Ctrl-C
  exit-decision stack --switch-to "" --no-visualizer --episodes 0
  # the conditioned MDGQN on the 81-action grid instead
  exit-decision stack --policy mdgqn_conditioned
'''


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Adds ``stack``."""
    from exit_decision.ros.stack.node_table import ARGUMENTS as STACK_ARGUMENTS   # rclpy-free, as this parser

    stack = commands.add_parser('stack', help='run the ROS 2 stack (bridge, graph builder, decision node, '
                                              'recorder) for an episode, with a mode switch',
                                   epilog=STACK_EXAMPLES)
    stack.add_argument('--config-dir', type=existing('dir'), default=None,
                       help='directory with scenario/graph/env/modes/reward YAML (default: config/)')
    start_mode = stack.add_argument(
        '--start-mode', default=None,
        help='decision mode at the start (default: the aggressive punished mode of config/modes.yaml\'s matrix)')
    renamed(stack, '--mode', start_mode)
    stack.add_argument('--switch-to', default=None,
                       help='mode to switch to mid-run ("" = no switch; default: the conservative punished mode '
                            'of config/modes.yaml\'s matrix)')
    stack.add_argument('--switch-at', type=STEP, default=300,
                       help='step of the first episode to switch at, below the scenario\'s max_steps')
    policy = stack.add_argument(
        '--policy', default=None,
        help='the policy the decision node runs: a directory name under policies/ (shipped, all mode-conditioned: '
             f'{", ".join(SHIPPED_ALGORITHMS)}), the path of a policy directory or of its policy.pt (a directory '
             'named as its algorithm, <method>[_options][_conditioned], or <method>_<mode> for a per-mode one), or '
             'a per-mode method (none ships: train them with --conditioning <mode>) as DIR/<method>, whose '
             f'DIR/<method>_<mode>/ directories hold a policy for each mode of the run; default: {DEFAULT_ALGORITHM}')
    renamed(stack, '--algorithm', policy)
    stack.add_argument('--policy-dir', action=Replaced, type=existing('dir'), default=None,
                       hint='give --policy DIR/<name> (a policy directory\'s path)')
    stack.add_argument('--episodes', type=number(int, 0), default=1,
                       help='episodes to run; 0: until stopped (Ctrl-C or SIGTERM stop the nodes and '
                            'finish the bag)')
    stack.add_argument('--seed', type=SEED, default=TEST_SEED, help='seed of the first episode, then +1 each')
    stack.add_argument('--bag', type=new_path, default=None,
                       help='bag directory, a new one (default: bags/exit_decision_<time>)')
    stack.add_argument('--compression', choices=STACK_ARGUMENTS['compression'].choices,
                       default=STACK_ARGUMENTS['compression'].default,
                       help='mcap chunk compression of the bag (default: %(default)s; one episode of the shipped '
                            'scenario, 80 s simulated: none 3.55 MB, zstd 0.49 MB)')
    stack.add_argument('--no-visualizer', action='store_true',
                       help='do not start the visualizer (no markers on /exit_decision/markers, none in the bag)')
    thread_priority_option(stack)
    cpu_split_option(stack)
    stack.set_defaults(func=cmd_stack)

"""The ``stack`` command: the whole ROS 2 stack in separate processes; and the options a run of
the nodes takes (real-time priority, the CPU split), ``bench ros``'s too."""
from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from exit_decision.config.seeds import TEST_SEED
from exit_decision.cli.arguments import SEED, STEP, OptionError, existing, known, known_algorithm, new_path, number
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


def cmd_stack(args: argparse.Namespace) -> int:
    """The whole ROS 2 stack in separate processes: an episode, a mode switch, a bag."""
    from datetime import datetime

    from exit_decision.evaluation import main_job
    from exit_decision.ros.stack.launcher import free_bag_path, run_stack

    config = load_project(args.config_dir)   # fail early, with the key, on a bad config
    check_thread_priority(args.thread_priority)
    matrix = config.mode_matrix
    known_algorithm(args.algorithm, config)
    mode = args.mode or matrix.aggressive.punished
    switch_to = matrix.conservative.punished if args.switch_to is None else args.switch_to or None
    known('--mode', mode, config.mode)
    if switch_to:
        known('--switch-to', switch_to, config.mode)
        if args.switch_at >= config.scenario.max_steps:
            raise OptionError(f'argument --switch-at: {args.switch_at}: expected a step below the scenario\'s '
                              f'max_steps ({config.scenario.max_steps}), or --switch-to "" for no switch')
    # another method than the shipped ones: the node loads its policies for the modes of this run only
    modes = [] if args.algorithm in SHIPPED_ALGORITHMS else [mode, *([switch_to] if switch_to else [])]
    stamp = f'{datetime.now():%Y%m%d_%H%M%S}'
    bag = args.bag or free_bag_path(Path('bags') / f'exit_decision_{stamp}')
    log_dir = Path('runs') / 'stack_logs' / stamp
    print(f'the stack: {args.algorithm} in {mode}' + (f', switched to {switch_to} at step {args.switch_at}' if switch_to
                                                        else '') +
          f', seed {args.seed}, {args.episodes or "episodes until stopped"}' + (' episode(s)' if args.episodes else ''),
          flush=True)
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
  exit-decision stack --mode CONI --switch-to AGGI --switch-at 200 --seed 10001 --bag bags/coni_to_aggi
  exit-decision show bags/coni_to_aggi
  # no switch, no visualizer, episodes until Ctrl-C
  exit-decision stack --switch-to "" --no-visualizer --episodes 0
  # the conditioned MDGQN on the 81-action grid instead
  exit-decision stack --algorithm mdgqn_conditioned
'''


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Adds ``stack``."""
    from exit_decision.ros.stack.node_table import ARGUMENTS as STACK_ARGUMENTS   # rclpy-free, as this parser

    stack = commands.add_parser('stack', help='run the ROS 2 stack (bridge, graph builder, decision node, '
                                              'recorder) for an episode, with a mode switch',
                                   epilog=STACK_EXAMPLES)
    stack.add_argument('--config-dir', type=existing('dir'), default=None,
                       help='directory with scenario/graph/env/modes/reward YAML (default: config/)')
    stack.add_argument('--mode', default=None,
                       help='decision mode at start (default: the aggressive punished mode of config/modes.yaml\'s matrix)')
    stack.add_argument('--switch-to', default=None,
                       help='mode to switch to mid-run ("" = no switch; default: the conservative punished mode '
                            'of config/modes.yaml\'s matrix)')
    stack.add_argument('--switch-at', type=STEP, default=300,
                       help='step of the first episode to switch at, below the scenario\'s max_steps')
    stack.add_argument('--algorithm', default=DEFAULT_ALGORITHM,
                       help='a learned method of config/training.yaml (<method>[_options][_conditioned]: over options; '
                            f'one network for every mode); shipped: {", ".join(SHIPPED_ALGORITHMS)} (others: '
                            '--policy-dir with <algorithm>_<mode>/policy.pt)')
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
    stack.add_argument('--policy-dir', type=existing('dir'), default=None,
                       help='directory of the policies, <algorithm>[_<mode>]/policy.pt (default: the shipped '
                            'policies/)')
    stack.add_argument('--no-visualizer', action='store_true',
                       help='do not start the visualizer (no markers on /exit_decision/markers, none in the bag)')
    thread_priority_option(stack)
    cpu_split_option(stack)
    stack.set_defaults(func=cmd_stack)

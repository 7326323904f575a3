"""The ``bench`` command: throughput figures of the simulation, learning, the sweep and the ROS stack."""
from __future__ import annotations

import argparse

from exit_decision.cli.arguments import COUNT, SEED, config_options, existing, number
from exit_decision.cli.stack import check_thread_priority, cpu_split_option, thread_priority_option
from exit_decision.config import load_project
from exit_decision.errors import UsageError
from exit_decision.ros.stack.flood import HUGE_BYTES_PER_S, KINDS   # free of rclpy


def cmd_bench(args: argparse.Namespace) -> int:
    """Print the throughput figures ``what`` names (sim, learning, sweep, ros; all: each)."""
    from exit_decision.benchmarks import bench_learning, bench_simulation
    config = load_project(args.config_dir, args.scenario_override, args.override)
    if args.topic:
        from exit_decision.ros.stack.node_table import ENDPOINTS
        subscribed = sorted({topic for endpoints in ENDPOINTS.values() for topic in endpoints.subscribes})
        for topic in args.topic:
            if topic not in subscribed:
                raise UsageError(f'--topic {topic}: no node of the stack subscribes to it; allowed: {", ".join(subscribed)}')
    if args.what in ('ros', 'all'):
        check_thread_priority(args.thread_priority)
    if args.what in ('sim', 'all'):
        print(bench_simulation(config, args.episodes, args.seed))
    if args.what in ('learning', 'all') and args.actors:
        from exit_decision.benchmarks import bench_actors
        print(bench_actors(args.config_dir, args.scenario_override, args.override, args.seed, args.actors,
                           args.training_episodes))
    elif args.what in ('learning', 'all'):
        print(bench_learning(args.config_dir, args.scenario_override, args.override, args.seed, args.episodes))
    if args.what in ('sweep', 'all'):
        from exit_decision.benchmarks import bench_sweep
        print(bench_sweep(args.config_dir, args.episodes, args.seed))
    if args.what in ('ros', 'all'):
        from exit_decision.ros.stack.bench import bench_ros
        print(bench_ros(str(args.config_dir or ''), str(args.policy_dir or ''), args.steps, args.seed,
                        args.thread_priority, cpu_split=not args.no_cpu_split))
    if args.what == 'flood':
        from exit_decision.ros.stack.flood import bench_flood, report
        text, ok = report(bench_flood(str(args.config_dir or ''), str(args.policy_dir or ''), args.seed,
                                      args.phase_seconds, args.pairs, args.topic, args.kind or KINDS, args.flooders,
                                      huge_bytes_per_s=args.huge_mb_per_s * 1e6))
        print(text)
        return 0 if ok else 1
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Adds ``bench``."""
    bench = commands.add_parser('bench', help='print throughput figures (simulation: libsumo vs TraCI; learning; '
                                              'the compare sweep with 1 and every local worker; ROS)')
    config_options(bench)
    bench.add_argument('what', nargs='?', choices=['sim', 'learning', 'sweep', 'ros', 'flood', 'all'], default='all',
                       help='what to measure: sim (libsumo vs TraCI), learning (steps per second, an update, a '
                            'decision), sweep (compare with 1 and every worker), ros (the stack), flood (the stack '
                            'while each topic it subscribes to is flooded; exit code 1 when a target is missed), '
                            'all (each in turn but flood)')
    bench.add_argument('--steps', type=COUNT, default=1000, help='ros: synchronous steps to measure')
    bench.add_argument('--policy-dir', type=existing('dir'), default=None, help='ros: directory of the policies (default: the shipped policies/)')
    bench.add_argument('--episodes', type=COUNT, default=2, help='episodes per measurement (sweep: seeds per cell)')
    bench.add_argument('--seed', type=SEED, default=0, help='the first seed')
    bench.add_argument('--actors', type=number(int, 0), action='append', default=None,
                       help='learning: instead of the update breakdown, train the shipped recipe with this many '
                            'Ray actors (0: in this process) and, with updates off, collect with them and with as '
                            'many plain processes (repeatable: one table; default: none)')
    bench.add_argument('--training-episodes', type=COUNT, default=50,
                       help='learning with --actors: training episodes per run')
    bench.add_argument('--phase-seconds', type=number(float, 0.0, inclusive=False), default=3.0,
                       help='flood: seconds of each flood, and of each phase without one after it')
    bench.add_argument('--pairs', type=COUNT, default=1, help='flood: pairs of phases (flood, none) per topic and kind')
    bench.add_argument('--topic', action='append', default=None,
                       help='flood: a topic to flood (repeatable; default: every topic the nodes subscribe to)')
    bench.add_argument('--kind', action='append', choices=KINDS, default=None,
                       help='flood: stale or oversized (repeatable; default: both)')
    bench.add_argument('--flooders', type=COUNT, default=2, help='flood: processes sending each flood')
    bench.add_argument('--huge-mb-per-s', type=number(float, 0.0), default=HUGE_BYTES_PER_S / 1e6,
                       help='flood: [MB/s] about how much of an oversized flood are huge messages (3601 x 3601 '
                            'arrays, 60,000 vehicles); 0: none, every one just over the limit')
    thread_priority_option(bench, 'ros: the benchmark\'s observer too, once the nodes are started; ')
    cpu_split_option(bench, 'ros: ')
    bench.set_defaults(func=cmd_bench)

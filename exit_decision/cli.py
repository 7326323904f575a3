"""The one command-line entry point: ``exit-decision <command> [options]``."""
from __future__ import annotations

import argparse
import math
import shlex
import signal
import sys
import zipfile
from pathlib import Path

from tqdm import tqdm

from exit_decision.config import ConfigError, default_config_dir, load_project
from exit_decision.errors import PolicyError, StackError, UsageError
from exit_decision.model.names import DEFAULT_ALGORITHM, policy_path


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--config-dir', type=existing('dir'), default=None,
                        help='directory with scenario/graph/env/modes/reward YAML (default: config/)')
    parser.add_argument('--scenario-override', type=existing('file'), default=None,
                        help='YAML merged over scenario.yaml (a scenario variant)')
    parser.add_argument('--override', type=existing('file'), action='append', default=[],
                        help='YAML keyed by config file (env:, graph:, training:, ...) merged over the '
                             'config (repeatable)')


def _thread_priority(parser: argparse.ArgumentParser, what: str = '') -> None:
    from exit_decision.ros.stack.realtime import DESCRIPTION, PRIORITIES

    def priority(text: str) -> int:
        if not text.isdigit() or int(text) not in PRIORITIES:
            raise argparse.ArgumentTypeError(f'{text!r} is not allowed; allowed: an integer in '
                                             f'{PRIORITIES[0]}..{PRIORITIES[-1]}')
        return int(text)
    parser.add_argument('--thread-priority', type=priority, default=0, metavar=f'{PRIORITIES[0]}-{PRIORITIES[-1]}',
                        help=what + DESCRIPTION)


def _cpu_split(parser: argparse.ArgumentParser, what: str = '') -> None:
    parser.add_argument('--no-cpu-split', action='store_true',
                        help=what + 'every node on every core, instead of the default with the normal scheduling: the '
                                    'decision path (bridge, graph builder, decision node) on the first half of the '
                                    'cores, the recorder and the visualizer on the rest')


class OptionError(UsageError):
    """An option's value the config refuses (an unknown mode, method, variant, step), found
    before any work; reported in argparse's words: ``exit-decision <command>: error: argument
    <option>: ...``, exit code 2."""


def _known(option: str, value, check) -> None:
    """Before any work: ``check(value)``, a lookup in the config that raises ConfigError for an
    unknown name, as an OptionError."""
    try:
        check(value)
    except ConfigError as error:
        raise OptionError(f'argument {option}: {error}') from None


def _known_algorithm(algorithm: str, config) -> None:
    """--algorithm: a learned method of the config, or <method>_conditioned (OptionError)."""
    from exit_decision.model.names import CONDITIONED_SUFFIX
    _known('--algorithm', algorithm.removesuffix(CONDITIONED_SUFFIX), config.training.method)


def _check_thread_priority(priority: int) -> None:
    """Before anything starts: a priority this user may not take is one line, not a node dying."""
    from exit_decision.ros.stack.realtime import refusal
    reason = refusal(priority) if priority else None
    if reason:
        raise UsageError(f'--thread-priority {reason}')


def cmd_run(args: argparse.Namespace) -> int:
    """Run episodes of the scenario and print the SPEC section 6 metrics."""
    import numpy as np

    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.metrics import markdown_table, summarize

    if args.variant and args.scenario_override:
        raise UsageError('--variant and --scenario-override: give one (a variant is a scenario override)')
    if args.variant:
        from exit_decision.experiments.compare import load_variants
        config = load_variants((args.config_dir or default_config_dir()) / 'variants.yaml', args.config_dir,
                               args.override, [args.variant])[args.variant]
    else:
        config = load_project(args.config_dir, args.scenario_override, args.override)
    if args.mode:
        _known('--mode', args.mode, config.mode)
    env = ExitDecisionEnv(config, mode=args.mode, cav_driver='sumo' if args.driver == 'sumo' else 'policy')
    hold = np.full(config.graph.max_vehicles, env.actions.index(0, 0.0))
    episodes, peak = [], 0
    try:
        for episode in tqdm(range(args.episodes), desc='episodes', unit='ep', disable=args.episodes == 1):
            env.reset(seed=args.seed + episode)
            done = False
            while not done:
                _, _, terminated, truncated, _ = env.step(hold)
                done = terminated or truncated
            episodes.append(env.episode_log.metrics())
            peak = max(peak, env.episode_log.peak_vehicles)
    finally:
        env.close()
    label = f'{args.driver} CAVs, reward {config.env.reward_variant}/{env.mode}'
    title = f'{args.episodes} episode(s), seeds {args.seed}..{args.seed + args.episodes - 1}, {label}'
    table = markdown_table([(label, summarize(episodes))])
    print(title)
    print(table)
    print(f'peak vehicles on the road at one step: {peak} (the graph holds N = {config.graph.max_vehicles})')
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(
            f'# {title}\n\nMade by `{args.invocation}` (mean ± std over episodes).\n\n{table}\n\n'
            f'## Configuration\n\n```json\n{config.model_dump_json(indent=2)}\n```\n', encoding='utf-8')
        print(f'table and configuration: {args.markdown}')
    if args.csv:
        from exit_decision.tables import write_rows
        write_rows(args.csv, [{'seed': args.seed + i, **row} for i, row in enumerate(episodes)])
        print(f'per-episode metrics: {args.csv}')
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    """Train a learned method (one mode or the conditioned network); writes policy.pt, logs and config."""
    from exit_decision.learning.trainer import Trainer
    from exit_decision.model.names import CONDITIONED

    config = load_project(args.config_dir, args.scenario_override, args.override)
    _known('--algorithm', args.algorithm, config.training.method)
    if args.mode != CONDITIONED:
        _known('--mode', args.mode, config.mode)
    episodes = args.episodes or config.training.episodes
    steps = config.training.of_method(args.algorithm).environment_steps
    if args.episodes and steps:
        raise UsageError(f'--episodes {args.episodes}: this config\'s budget for {args.algorithm} is environment_steps: '
                         f'{steps}; give one budget (drop --episodes, or set environment_steps to null with --override)')
    out_dir = args.out or Path('runs') / f'{args.algorithm}_{args.mode}_seed{args.seed}'
    if args.reward_variant:
        _known('--reward-variant', args.reward_variant, config.reward)
        config = config.model_copy(update={'env': config.env.model_copy(update={'reward_variant': args.reward_variant})})
    trainer = Trainer(config, args.algorithm, args.mode, args.seed, out_dir, args.action_space)
    policy = trainer.run(episodes, resume=args.resume, init=args.init)
    print(f'best policy: {policy} (validation score {trainer.state.best_score:.3f}); logs in {out_dir}')
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate policies and/or the reference drivers on fixed seeds; print and save the table."""
    from exit_decision.evaluation.report import evaluate_runs

    config = load_project(args.config_dir, args.scenario_override, args.override)
    if not args.policy and not args.driver:
        raise OptionError('nothing to evaluate: give --policy or --driver (each repeatable)')
    for mode in args.mode:
        _known('--mode', mode, config.mode)
    modes = args.mode or list(config.training.conditioning.validation_modes)
    sanity_drivers = {}
    if any(':' in driver for driver in args.driver):
        from exit_decision.experiments.reward_sanity import load_sweep
        sanity_drivers, _ = load_sweep((args.config_dir or default_config_dir()) / 'reward_sanity.yaml', config)
        for driver in args.driver:
            if driver.partition(':')[2] and driver.partition(':')[2] not in sanity_drivers:
                raise ConfigError(f'--driver {driver}: no such driver in reward_sanity.yaml; known: '
                                  f'{", ".join(sanity_drivers)}')
    show = None
    if args.show:
        from exit_decision.visualization.episodes import ShowEpisodes
        show = ShowEpisodes(args.out / 'show', min(args.show, args.episodes))
    table = evaluate_runs(config, policies=args.policy, drivers=args.driver, modes=modes, episodes=args.episodes,
                          sanity_drivers=sanity_drivers, show=show,
                          seed=args.seed, out_dir=args.out, command=args.invocation)
    print(table)
    if show:
        print(f'time-space diagrams and bird\'s-eye clips of the first {show.episodes} episode(s) of each run: '
              f'{show.out_dir}')
    return 0


def cmd_ablation(args: argparse.Namespace) -> int:
    """Train and evaluate each step of config/ablation.yaml; print the table."""
    from exit_decision.experiments.ablation import markdown, run_ablation

    config = load_project(args.config_dir)
    mode = args.mode or config.env.mode
    _known('--algorithm', args.algorithm, config.training.method)
    _known('--mode', mode, config.mode)
    if args.only:
        from exit_decision.experiments.ablation import ablation_steps
        steps = len(ablation_steps((args.config_dir or default_config_dir()) / 'ablation.yaml'))
        for index in args.only:
            if index >= steps:
                raise OptionError(f'argument --only: {index}: expected a step index of ablation.yaml, '
                                  f'0..{steps - 1}')
    table = run_ablation(args.out, args.algorithm, mode, args.episodes, args.test_episodes, args.seed,
                         args.test_seed, args.only, args.config_dir)
    print(markdown(table))
    return 0


def cmd_reward_sanity(args: argparse.Namespace) -> int:
    """Score a sweep of rule-based drivers under every mode (before any training)."""
    from exit_decision.experiments.reward_sanity import calibrate, load_sweep, write_sanity
    from exit_decision.tables import read_rows

    config = load_project(args.config_dir, args.scenario_override, args.override)
    sweep = args.sweep or (args.config_dir or default_config_dir()) / 'reward_sanity.yaml'
    for variant in args.variant:
        _known('--variant', variant, config.reward)
    variants = args.variant or [config.env.reward_variant]
    if args.calibrate:
        episodes = args.out / 'episodes.csv'
        if not episodes.is_file():
            raise ConfigError(f'{episodes}: no such file (run reward-sanity without --calibrate first)')
        drivers, expect = load_sweep(sweep, config)
        for variant in variants:
            print(calibrate(read_rows(episodes), config, variant, next(iter(drivers)), expect))
        return 0
    print(write_sanity(config, sweep, list(range(args.seed, args.seed + args.episodes)), variants, args.jobs,
                       args.out, args.invocation, args.low_level))
    return 0


def cmd_options_table(args: argparse.Namespace) -> int:
    """Every constant option under every mode, beside the grid's teacher and SUMO's drivers."""
    from exit_decision.experiments.constant_options import write_table

    config = load_project(args.config_dir, args.scenario_override, args.override)
    for variant in args.variant:
        _known('--variant', variant, config.reward)
    if args.policy is not None:
        from exit_decision.model.policy import load_policy
        load_policy(args.policy).check_compatible(config)
    print(write_table(config, list(range(args.seed, args.seed + args.episodes)),
                      args.variant or [config.env.reward_variant], args.jobs, args.out, args.invocation, args.policy))
    return 0


def cmd_tradeoff(args: argparse.Namespace) -> int:
    """A conditioned policy at every weight point: speed against hard braking and safety."""
    from exit_decision.experiments.tradeoff import run_tradeoff

    config = load_project(args.config_dir, args.scenario_override, args.override)
    print(run_tradeoff(config, args.policy, list(range(args.seed, args.seed + args.episodes)), args.out))
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """Write the results page from evaluation, ablation and figures."""
    from exit_decision.evaluation.report import results_page

    config = load_project(args.config_dir)
    print(results_page(args.evaluation, args.runs, args.sanity, args.tradeoff, args.figures, args.out,
                       max_steps=config.scenario.max_steps, speed_pairs=config.mode_matrix.speed_orderings))
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """PNG figures from training runs and an evaluation directory."""
    from exit_decision.evaluation.plots import make_all

    for path in make_all(args.runs, args.evaluation, args.out):
        print(path)
    return 0


def cmd_stack(args: argparse.Namespace) -> int:
    """The whole ROS 2 stack in separate processes: an episode, a mode switch, a bag."""
    from datetime import datetime

    from exit_decision.evaluation.metrics import markdown_table, summarize
    from exit_decision.ros.stack.launcher import free_bag_path, run_stack

    from exit_decision.model.names import SHIPPED_ALGORITHMS

    config = load_project(args.config_dir)   # fail early, with the key, on a bad config
    _check_thread_priority(args.thread_priority)
    matrix = config.mode_matrix
    _known_algorithm(args.algorithm, config)
    mode = args.mode or matrix.aggressive.punished
    switch_to = matrix.conservative.punished if args.switch_to is None else args.switch_to or None
    _known('--mode', mode, config.mode)
    if switch_to:
        _known('--switch-to', switch_to, config.mode)
        if args.switch_at >= config.scenario.max_steps:
            raise OptionError(f'argument --switch-at: {args.switch_at}: expected a step below the scenario\'s '
                              f'max_steps ({config.scenario.max_steps}), or --switch-to "" for no switch')
    # another method than the shipped ones: the node loads its policies for the modes of this run only
    modes = [] if args.algorithm in SHIPPED_ALGORITHMS else [mode, *([switch_to] if switch_to else [])]
    stamp = f'{datetime.now():%Y%m%d_%H%M%S}'
    bag = args.bag or free_bag_path(Path('bags') / f'exit_decision_{stamp}')
    run = run_stack(mode=mode, modes=modes, algorithm=args.algorithm, episodes=args.episodes, seed=args.seed,
                    bag_path=bag, log_dir=Path('runs') / 'stack_logs' / stamp,
                    switch_to=switch_to, switch_at_step=args.switch_at,
                    config_dir=str(args.config_dir or ''), policy_dir=str(args.policy_dir or ''),
                    visualizer=not args.no_visualizer, thread_priority=args.thread_priority,
                    cpu_split=not args.no_cpu_split, compression=args.compression)
    if run.stopped_by:
        print(f'stopped by {run.stopped_by}: {len(run.episodes)} episode(s) finished; the nodes stopped')
    if run.mode_switch:
        print(run.mode_switch)
    elif switch_to:
        print(f'no mode switch: the first episode did not reach step {args.switch_at}')
    if run.episodes:
        switched = run.mode_switch.endswith('accepted')
        label = f'{args.algorithm} {mode}' + (f' -> {switch_to}' if switched else '')
        print(markdown_table([(label, summarize(run.episodes))]))
    else:
        print('no episode finished' + ('' if run.stopped_by else ' (see the logs)'))
    print(f'bag: {bag}')
    failed = {name: code for name, code in run.return_codes.items() if code not in (0, -2, -9)}
    if failed:
        print(f'nodes that failed: {failed}', file=sys.stderr)
        return 1
    if run.stopped_by:   # until stopped (--episodes 0): the end asked for; else the run was cut short
        return 0 if args.episodes == 0 else 128 + signal.Signals[run.stopped_by].value
    return 0 if run.episodes else 1


def cmd_replay(args: argparse.Namespace) -> int:
    """Re-run the decision policy on a bag's recorded graphs; compare with its commands."""
    from exit_decision.ros.bags.storage import BagError
    from exit_decision.model.names import default_policy_dir
    from exit_decision.ros.bags.replay import replay_decisions

    config = load_project(args.config_dir, args.scenario_override, args.override)
    if args.mode:
        _known('--mode', args.mode, config.mode)
    if args.algorithm:
        _known_algorithm(args.algorithm, config)
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


def cmd_compare(args: argparse.Namespace) -> int:
    """Train the learned methods (``--train``), then every method on every scenario variant, the
    same seeds, as Ray tasks; CSV per cell; the comparison page and its figures."""
    from exit_decision.experiments.compare import (REFERENCE_DRIVERS, SweepResult, default_methods,
                                                   load_comparison_training, load_variants, plan_cells, run_sweep,
                                                   run_trainings)
    from exit_decision.experiments.comparison_report import write_comparison

    config_dir = args.config_dir or default_config_dir()
    configs = load_variants(args.variants or config_dir / 'variants.yaml', args.config_dir, args.override,
                            args.variant)
    base = next(iter(configs.values()))
    for mode in args.mode:
        _known('--mode', mode, base.mode)
    modes = args.mode or list(base.training.conditioning.validation_modes)
    methods = base.training.method_names if args.train == ['all'] else args.train
    for method in methods:
        _known('--train', method, base.training.method)
    runs, trained, training_mode, budget, trainings = [], {}, base.env.mode, None, SweepResult()
    if methods:
        runs, budgeted, budget = load_comparison_training(args.training or config_dir / 'comparison.yaml',
                                                          load_project(args.config_dir, overrides=args.override), methods)
        training_mode = runs[0].mode
        if args.report_only:   # the runs whose logs the results hold; no checkpoint read
            trained = {run.name: None for run in runs if run.logged(args.out)}
        else:
            trainings = run_trainings(runs, budgeted, args.policies, args.out, args.address, args.workers,
                                      args.retries)
            trained = {run.name: run.directory(args.policies) / 'policy.pt' for run in runs
                       if run.done(args.policies, budgeted)}
    drivers = args.method or (list(REFERENCE_DRIVERS) if methods else default_methods())
    cells = plan_cells(drivers, configs, modes, {} if args.report_only else trained)
    seeds = list(range(args.seed, args.seed + args.episodes))
    if not args.report_only:
        result = run_sweep(cells, configs, seeds, args.out, args.address, args.workers, args.retries)
    learned = {method: [run.name for run in runs if run.method == method and run.name in trained] for method in methods}
    # the page says the command that made its results: a rebuild from them says the same
    command = args.invocation.replace(' --report-only', '') if args.report_only else args.invocation
    report = write_comparison(args.out, args.report or args.out / 'comparison.md', list(configs), learned,
                              sorted({cell.method for cell in cells if cell.method not in trained}),
                              modes, training_mode, base.scenario.max_steps,
                              command, budget,
                              [method for method in base.training.method_names if method not in methods])
    if args.report_only:
        print(f'the comparison, from the CSVs in {args.out}: {report}')
        return 0
    if methods:
        print('training: ' + trainings.summary())
    print(result.summary())
    print(f'per-cell CSVs in {args.out}/<variant>/; the comparison: {report}')
    return 1 if result.failed or trainings.failed else 0


def cmd_bench(args: argparse.Namespace) -> int:
    from exit_decision.benchmarks import bench_learning, bench_simulation
    config = load_project(args.config_dir, args.scenario_override, args.override)
    if args.what in ('ros', 'all'):
        _check_thread_priority(args.thread_priority)
    if args.what in ('sim', 'all'):
        print(bench_simulation(config, args.episodes, args.seed))
    if args.what in ('learning', 'all'):
        print(bench_learning(config, args.seed, args.episodes))
    if args.what in ('sweep', 'all'):
        from exit_decision.benchmarks import bench_sweep
        print(bench_sweep(args.config_dir, args.episodes, args.seed))
    if args.what in ('ros', 'all'):
        from exit_decision.ros.stack.bench import bench_ros
        print(bench_ros(str(args.config_dir or ''), str(args.policy_dir or ''), args.steps, args.seed,
                        args.thread_priority, cpu_split=not args.no_cpu_split))
    return 0


def reference_driver(text: str) -> str:
    """``sumo``, ``rule_based`` or ``rule_based:<name>`` (the name is checked against the sweep later)."""
    name, colon, variant = text.partition(':')
    if name == 'sumo' and not colon or name == 'rule_based' and (not colon or variant):
        return text
    raise argparse.ArgumentTypeError(f'{text!r}: expected sumo, rule_based or rule_based:<driver of reward_sanity.yaml>')


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


def comparison_method(text: str) -> str:
    """An argparse type: a reference driver or a policy checkpoint (compare --method)."""
    from exit_decision.evaluation.report import REFERENCE_DRIVERS
    if text in REFERENCE_DRIVERS:
        return text
    try:
        return str(checkpoint(text))
    except argparse.ArgumentTypeError as error:
        raise argparse.ArgumentTypeError(f'{error}; allowed: {", ".join(REFERENCE_DRIVERS)} or a policy.pt') from None


class Parser(argparse.ArgumentParser):
    """argparse's parser, its usage errors in one line (argument, value, what is allowed) and
    exit code 2; the usage is in --help."""

    def error(self, message: str):
        self.exit(2, f'{self.prog}: error: {message}\n')


#: option types: counts, seeds and step numbers
COUNT, SEED, STEP = number(int, 1), number(int, 0), number(int, 0)


def build_parser() -> argparse.ArgumentParser:
    from exit_decision.ros.stack.node_table import ARGUMENTS as STACK_ARGUMENTS   # rclpy-free, as this parser

    parser = Parser(prog='exit-decision', description=__doc__)
    commands = parser.add_subparsers(dest='command', required=True)

    run = commands.add_parser('run', help='run episodes of the scenario and print the metrics table')
    _common(run)
    run.add_argument('--episodes', type=COUNT, default=1)
    run.add_argument('--seed', type=SEED, default=0, help='seed of the first episode (then +1 each)')
    run.add_argument('--driver', choices=['sumo', 'hold'], default='sumo',
                     help='who drives the CAVs: sumo = SUMO\'s own drivers, routed to the target exit (the '
                          'rule-based reference); hold = the policy interface with SUMO\'s safety off, '
                          'every CAV holding lane and speed (shows that collisions are real)')
    run.add_argument('--mode', default=None, help='decision mode for the reward (default: env.yaml)')
    run.add_argument('--variant', default=None, help='a cell of config/variants.yaml (e.g. density_1.45)')
    run.add_argument('--csv', type=Path, default=None, help='write per-episode metrics here')
    run.add_argument('--markdown', type=Path, default=None,
                     help='write the table with the command and the full configuration here')
    run.set_defaults(func=cmd_run)

    train = commands.add_parser('train', help='train a learned method (GQN, MDGQN, the baselines) for a mode or all')
    _common(train)
    train.add_argument('--algorithm', default='mdgqn',
                       help='a method of config/training.yaml: gqn, mdgqn, dqn, ddqn, dueling_dqn, dueling_ddqn_per, '
                            'dueling_ddqn, sgrl, mgrl, ngrl, and each baseline as published (<name>_published, e.g. dqn_published)')
    train.add_argument('--mode', default='conditioned',
                       help='conditioned (one network for every mode, trained on all by relabelling) or a '
                            'mode of config/modes.yaml (a per-mode network)')
    train.add_argument('--episodes', type=COUNT, default=None,
                       help="RL episodes (default: config/training.yaml's episodes; refused when the config's budget "
                            "is environment_steps)")
    train.add_argument('--seed', type=SEED, default=0)
    train.add_argument('--out', type=Path, default=None, help='run directory (default runs/<alg>_<mode>_seed<s>)')
    train.add_argument('--resume', type=checkpoint, default=None, help='a last.pt to continue from')
    train.add_argument('--init', type=checkpoint, default=None,
                       help='a policy.pt whose network starts the RL phase (no pre-training)')
    train.add_argument('--reward-variant', default=None, help='a variant of config/reward.yaml (default: env.yaml)')
    train.add_argument('--action-space', choices=['grid', 'options'], default='grid',
                       help='the 81-action grid (paper 000) or options (config/env.yaml options: a lane intent x a '
                            'driving style, held until it ends, executed by the rule-based low level)')
    train.set_defaults(func=cmd_train)

    evaluate = commands.add_parser('evaluate', help='evaluate policies / reference drivers on fixed seeds')
    _common(evaluate)
    evaluate.add_argument('--policy', type=checkpoint, action='append', default=[], help='a policy.pt (repeatable)')
    evaluate.add_argument('--driver', action='append', default=[], type=reference_driver,
                          help='a reference driver (repeatable): sumo (SUMO\'s own drivers), rule_based '
                               '(the neutral teacher, env.yaml\'s rule_based) or rule_based:<name> (a driver '
                               'of config/reward_sanity.yaml)')
    evaluate.add_argument('--mode', action='append', default=[],
                          help='score (and run a conditioned policy) under this mode (repeatable; default: '
                               'training.yaml conditioning.validation_modes); one CSV per run and mode')
    evaluate.add_argument('--episodes', type=COUNT, default=50)
    evaluate.add_argument('--seed', type=SEED, default=10_000, help='first test seed (never used in training)')
    evaluate.add_argument('--out', type=Path, default=Path('runs/evaluation'),
                          help='directory for the CSV and Markdown tables')
    evaluate.add_argument('--show', type=number(int, 0), default=0, metavar='N',
                          help='draw the first N episodes of each run into --out/show/: time-space diagram (PNG) '
                               'and bird\'s-eye clip (GIF; MP4 too where ffmpeg exists)')
    evaluate.set_defaults(func=cmd_evaluate)

    stack = commands.add_parser('stack', help='run the ROS 2 stack (bridge, graph builder, decision node, '
                                              'recorder) for an episode, with a mode switch')
    stack.add_argument('--config-dir', type=existing('dir'), default=None)
    stack.add_argument('--mode', default=None,
                       help='decision mode at start (default: the aggressive punished mode of config/modes.yaml\'s matrix)')
    stack.add_argument('--switch-to', default=None,
                       help='mode to switch to mid-run ("" = no switch; default: the conservative punished mode '
                            'of config/modes.yaml\'s matrix)')
    stack.add_argument('--switch-at', type=STEP, default=300,
                       help='step of the first episode to switch at (below the scenario\'s max_steps)')
    stack.add_argument('--algorithm', default=DEFAULT_ALGORITHM,
                       help='a learned method of config/training.yaml, <method>_conditioned for one network for every '
                            f'mode; shipped policies: {DEFAULT_ALGORITHM}, gqn, mdgqn (others: --policy-dir with '
                            '<algorithm>_<mode>/policy.pt)')
    stack.add_argument('--episodes', type=number(int, 0), default=1,
                       help='episodes to run (default 1); 0: until stopped (Ctrl-C or SIGTERM stop the nodes and '
                            'finish the bag)')
    stack.add_argument('--seed', type=SEED, default=10_000)
    stack.add_argument('--bag', type=new_path, default=None,
                       help='bag directory, a new one (default bags/exit_decision_<time>)')
    stack.add_argument('--compression', choices=STACK_ARGUMENTS['compression'].choices,
                       default=STACK_ARGUMENTS['compression'].default,
                       help='mcap chunk compression of the bag (default %(default)s; one episode of the shipped '
                            'scenario, 80 s simulated: none 3.55 MB, zstd 0.49 MB)')
    stack.add_argument('--policy-dir', type=existing('dir'), default=None, help='default: the shipped policies/')
    stack.add_argument('--no-visualizer', action='store_true',
                       help='do not start the visualizer (no markers on /exit_decision/markers, none in the bag)')
    _thread_priority(stack)
    _cpu_split(stack)
    stack.set_defaults(func=cmd_stack)

    replay = commands.add_parser('replay', help='re-run the policy on a bag and compare with its commands')
    _common(replay)
    replay.add_argument('bag', type=Path)
    replay.add_argument('--mode', default=None, help='replay with this mode (default: the recorded one)')
    replay.add_argument('--algorithm', default=None,
                        help='replay with this learned method\'s policies in --policy-dir (default: the recorded one)')
    replay.add_argument('--policy', type=checkpoint, default=None, help='a policy.pt to replay with instead')
    replay.add_argument('--policy-dir', type=existing('dir'), default=None)
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
                      help='the config the bag was recorded with (the road)')
    show.add_argument('--episode', type=number(int, 0), default=None, help='only this episode (default: every one)')
    show.add_argument('--start', type=number(float, 0), default=None, help='[s] simulation time the window starts at')
    show.add_argument('--end', type=number(float, 0), default=None, help='[s] simulation time the window ends at')
    show.add_argument('--speed', type=number(float, 0, inclusive=False), default=5.0,
                      help='clip speed, times real time (default 5)')
    show.add_argument('--fps', type=number(float, 0, inclusive=False), default=10.0,
                      help='clip frames per second (default 10)')
    show.set_defaults(func=cmd_show)

    ablation = commands.add_parser('ablation', help='train + evaluate each step of config/ablation.yaml')
    ablation.add_argument('--config-dir', type=existing('dir'), default=None)
    ablation.add_argument('--algorithm', default='mdgqn', help='a method of config/training.yaml')
    ablation.add_argument('--mode', default=None, help='decision mode (default: env.yaml\'s mode)')
    ablation.add_argument('--episodes', type=COUNT, default=40, help='training episodes per step')
    ablation.add_argument('--test-episodes', type=COUNT, default=10)
    ablation.add_argument('--seed', type=SEED, default=0)
    ablation.add_argument('--test-seed', type=SEED, default=10_000)
    ablation.add_argument('--only', type=STEP, nargs='*', default=None, help='step indices to run')
    ablation.add_argument('--out', type=Path, default=Path('runs/ablation'))
    ablation.set_defaults(func=cmd_ablation)

    sanity = commands.add_parser('reward-sanity', help='score a sweep of rule-based drivers under every mode')
    _common(sanity)
    sanity.add_argument('--sweep', type=existing('file'), default=None,
                        help='drivers (default: config/reward_sanity.yaml)')
    sanity.add_argument('--variant', action='append', default=[],
                        help='reward variant to score under (repeatable; default: env.yaml\'s)')
    sanity.add_argument('--episodes', type=COUNT, default=30, help='paired seeds per driver')
    sanity.add_argument('--seed', type=SEED, default=20_000, help='first seed (not a test or training seed)')
    sanity.add_argument('--jobs', type=COUNT, default=2, help='worker processes (one simulation each)')
    sanity.add_argument('--out', type=Path, default=Path('docs/results/reward_sanity'))
    sanity.add_argument('--low-level', choices=['grid', 'options'], default='grid',
                        help='the drivers on the action grid, or off it with the options\' low level '
                             '(env.yaml options.low_level)')
    sanity.add_argument('--calibrate', action='store_true',
                        help='no simulation: search row-scale multipliers on --out\'s episodes.csv')
    sanity.set_defaults(func=cmd_reward_sanity)

    options = commands.add_parser('options-table', help='every constant option under every mode (the best '
                                                         'fixed driver per mode), with the references')
    _common(options)
    options.add_argument('--episodes', type=COUNT, default=50, help='paired seeds per run')
    options.add_argument('--seed', type=SEED, default=900_000,
                         help='first seed (default: the validation seeds; 10000: the test seeds)')
    options.add_argument('--variant', action='append', default=[],
                         help='reward variant to score under (repeatable; default: env.yaml\'s)')
    options.add_argument('--policy', type=checkpoint, default=None,
                         help='a policy.pt (grid or options) to judge against the best fixed driver of each mode '
                              'and SUMO\'s drivers on the same seeds')
    options.add_argument('--jobs', type=COUNT, default=2, help='worker processes (one simulation each)')
    options.add_argument('--out', type=Path, default=Path('docs/results/options'))
    options.set_defaults(func=cmd_options_table)

    tradeoff = commands.add_parser('tradeoff', help='a conditioned policy at every weight point (figure)')
    _common(tradeoff)
    tradeoff.add_argument('--policy', type=checkpoint, default=policy_path(Path('policies'), DEFAULT_ALGORITHM))
    tradeoff.add_argument('--episodes', type=COUNT, default=20, help='seeds per weight point')
    tradeoff.add_argument('--seed', type=SEED, default=40_000, help='first seed (not a test or training seed)')
    tradeoff.add_argument('--out', type=Path, default=Path('docs/results/tradeoff'))
    tradeoff.set_defaults(func=cmd_tradeoff)

    plot = commands.add_parser('plot', help='PNG figures from training runs and evaluation results')
    plot.add_argument('--runs', type=existing('dir'), nargs='*', default=[], help='training run directories')
    plot.add_argument('--evaluation', type=existing('dir'), default=None, help='an evaluate --out directory')
    plot.add_argument('--out', type=Path, default=Path('docs/figures'))
    plot.set_defaults(func=cmd_plot)

    report = commands.add_parser('report', help='write docs/results.md from the generated results')
    report.add_argument('--evaluation', type=existing('dir'), default=Path('docs/results/evaluation'))
    report.add_argument('--config-dir', type=existing('dir'), default=None)
    report.add_argument('--runs', type=existing('dir'), nargs='*', default=[Path('policies') / DEFAULT_ALGORITHM],
                        help='training run directories (validation history, wall time)')
    report.add_argument('--sanity', type=existing('dir'), default=Path('docs/results/reward_sanity'))
    report.add_argument('--tradeoff', type=existing('dir'), default=Path('docs/results/tradeoff'))
    report.add_argument('--figures', type=existing('dir'), default=Path('docs/figures'))
    report.add_argument('--out', type=Path, default=Path('docs/results.md'))
    report.set_defaults(func=cmd_report)

    compare = commands.add_parser('compare', help='every method on every scenario variant (config/variants.yaml) on '
                                                  'the same seeds, as Ray tasks; a CSV per cell, reruns skip done cells')
    compare.add_argument('--config-dir', type=existing('dir'), default=None)
    compare.add_argument('--override', type=existing('file'), action='append', default=[],
                         help='YAML keyed by config file merged over the config of every variant (repeatable)')
    compare.add_argument('--variants', type=existing('file'), default=None, help='default: <config dir>/variants.yaml')
    compare.add_argument('--variant', action='append', default=[], help='only this cell of the file (repeatable)')
    compare.add_argument('--method', type=comparison_method, action='append', default=[],
                         help='rule_based, sumo or a policy.pt (repeatable; default: both drivers, and the shipped '
                              f'policies/{DEFAULT_ALGORITHM}/policy.pt unless --train is given)')
    compare.add_argument('--train', action='append', default=[],
                         help='a method of config/training.yaml to train (repeatable; "all": every one) on the base '
                              'scenario, with the seeds and budget of --training; finished runs are reused')
    compare.add_argument('--training', type=existing('file'), default=None,
                         help='default: <config dir>/comparison.yaml')
    compare.add_argument('--policies', type=Path, default=Path('policies/comparison'),
                         help='where each --train run trains and keeps its policy.pt (<policies>/<method>_s<seed>/, '
                              'beside its config.json and timing.json), reused when done with the same settings; '
                              'its logs are copied to <out>/training/ for the page (default: %(default)s, the runs '
                              'of docs/comparison.md)')
    compare.add_argument('--report-only', action='store_true',
                         help='only write the page from the CSVs and training logs in --out (no training, no '
                              'simulation, no checkpoint of a --train run read)')
    compare.add_argument('--report', type=Path, default=None,
                         help='the comparison page (figures beside it; default <out>/comparison.md)')
    compare.add_argument('--mode', action='append', default=[],
                         help='score under this mode (repeatable; default: training.yaml conditioning.validation_modes)')
    compare.add_argument('--episodes', type=number(int, 1), default=30, help='seeds per cell')
    compare.add_argument('--seed', type=SEED, default=10_000, help='first test seed (never used in training)')
    compare.add_argument('--out', type=Path, default=Path('runs/compare'))
    compare.add_argument('--address', default=None,
                         help='a Ray cluster to run on (its nodes need this package, SUMO and the policy files); '
                              'default: a local Ray on loopback')
    compare.add_argument('--workers', type=number(int, 1), default=None,
                         help='local Ray: simulations at once (default: every core)')
    compare.add_argument('--retries', type=number(int, 0), default=2, help='further attempts of a failed cell')
    compare.set_defaults(func=cmd_compare)

    bench = commands.add_parser('bench', help='print throughput figures (simulation: libsumo vs TraCI; learning; '
                                              'the compare sweep with 1 and every local worker; ROS)')
    _common(bench)
    bench.add_argument('what', nargs='?', choices=['sim', 'learning', 'sweep', 'ros', 'all'], default='all')
    bench.add_argument('--steps', type=COUNT, default=1000, help='ros: synchronous steps to measure')
    bench.add_argument('--policy-dir', type=existing('dir'), default=None, help='ros: default the shipped policies/')
    bench.add_argument('--episodes', type=COUNT, default=2, help='episodes per measurement (sweep: seeds per cell)')
    bench.add_argument('--seed', type=SEED, default=0)
    _thread_priority(bench, 'ros: the benchmark\'s observer too, once the nodes are started; ')
    _cpu_split(bench, 'ros: ')
    bench.set_defaults(func=cmd_bench)
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


if __name__ == '__main__':
    sys.exit(main())

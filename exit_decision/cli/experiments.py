"""The sweeps: ``ablation``, ``reward-sanity``, ``options-table``, ``tradeoff`` and ``compare``
(every method on every scenario variant, as Ray tasks)."""
from __future__ import annotations

import argparse
from pathlib import Path

from exit_decision.config.seeds import SANITY_SEED, TEST_SEED, VALIDATION_SEED
from exit_decision.cli.arguments import (COUNT, SEED, STEP, OptionError, Repeated, config_options, existing, known,
                                         number, policy, renamed)
from exit_decision.config import ConfigError, default_config_dir, load_project
from exit_decision.model.names import DEFAULT_ALGORITHM, GRID_ALGORITHM, policy_path


def cmd_ablation(args: argparse.Namespace) -> int:
    """Train and evaluate each step of config/ablation.yaml; print the table."""
    from exit_decision.experiments.ablation import markdown, run_ablation

    config = load_project(args.config_dir)
    mode = args.score_mode or config.env.mode
    known('--algorithm', args.algorithm, config.training.method)
    known('--score-mode', mode, config.mode)
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
    for variant in args.reward_variant:
        known('--reward-variant', variant, config.reward)
    variants = args.reward_variant or [config.env.reward_variant]
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
    for variant in args.reward_variant:
        known('--reward-variant', variant, config.reward)
    from exit_decision.experiments.constant_options import policy_label
    from exit_decision.model.policy import load_policy
    policies = {}
    for path in args.policy:
        load_policy(path).check_compatible(config)
        if policy_label(path) in policies:
            raise OptionError(f'--policy {path}: a second policy named {policy_label(path)!r}; allowed: one policy per run '
                              f'directory and file name')
        policies[policy_label(path)] = path
    print(write_table(config, list(range(args.seed, args.seed + args.episodes)),
                      args.reward_variant or [config.env.reward_variant], args.jobs, args.out, args.invocation, policies))
    return 0


def cmd_tradeoff(args: argparse.Namespace) -> int:
    """A conditioned policy at every weight point: speed against hard braking and safety."""
    from exit_decision.experiments.tradeoff import redraw_tradeoff, run_tradeoff

    config = load_project(args.config_dir, args.scenario_override, args.override)
    if args.plot_only:
        print(redraw_tradeoff(config, args.policy, args.episodes, args.out))
        return 0
    print(run_tradeoff(config, args.policy, list(range(args.seed, args.seed + args.episodes)), args.out))
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    """Train the learned methods (``--train``), then every method on every scenario variant, the
    same seeds, as Ray tasks; CSV per cell; the comparison page and its figures."""
    from exit_decision.config import load_variants
    from exit_decision.experiments.compare import (REFERENCE_DRIVERS, SweepResult, default_methods,
                                                   load_comparison_training, plan_cells, run_sweep, run_trainings)
    from exit_decision.experiments.comparison_report import write_comparison

    config_dir = args.config_dir or default_config_dir()
    configs = load_variants(args.scenario_variants or config_dir / 'variants.yaml', args.config_dir, args.override,
                            args.scenario_variant)
    base = next(iter(configs.values()))
    for mode in args.score_mode:
        known('--score-mode', mode, base.mode)
    modes = args.score_mode or list(base.training.conditioning.validation_modes)
    methods = base.training.method_names if args.train == ['all'] else args.train
    for method in methods:
        known('--train', method, base.training.method)
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


def comparison_method(text: str) -> str:
    """An argparse type: a reference driver or a policy checkpoint (compare --method)."""
    from exit_decision.evaluation.report import REFERENCE_DRIVERS
    if text in REFERENCE_DRIVERS:
        return text
    try:
        return str(policy(text))
    except argparse.ArgumentTypeError as error:
        raise argparse.ArgumentTypeError(f'{error}; or {", ".join(REFERENCE_DRIVERS)}') from None


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Adds ``ablation``, ``reward-sanity``, ``options-table``, ``tradeoff`` and ``compare``."""
    ablation = commands.add_parser('ablation', help='train + evaluate each step of config/ablation.yaml')
    ablation.add_argument('--config-dir', type=existing('dir'), default=None,
                          help='directory with scenario/graph/env/modes/reward YAML (default: config/)')
    ablation.add_argument('--algorithm', default='mdgqn', help='a method of config/training.yaml')
    renamed(ablation, '--mode', ablation.add_argument(
        '--score-mode', default=None,
        help='the mode each step is scored under, and trained for where a step trains one mode (default: env.yaml\'s '
             'mode)'))
    ablation.add_argument('--episodes', type=COUNT, default=40, help='training episodes per step')
    ablation.add_argument('--test-episodes', type=COUNT, default=10, help='test episodes per step')
    ablation.add_argument('--seed', type=SEED, default=0, help='training seed')
    ablation.add_argument('--test-seed', type=SEED, default=TEST_SEED, help='the first test seed')
    ablation.add_argument('--only', type=STEP, action=Repeated, default=None,
                          help='a step index to run, its place in config/ablation.yaml (repeatable; default: every '
                               'step)')
    ablation.add_argument('--out', type=Path, default=Path('runs/ablation'), help='where the runs go')
    ablation.set_defaults(func=cmd_ablation)

    sanity = commands.add_parser('reward-sanity', help='score a sweep of rule-based drivers under every mode')
    config_options(sanity)
    sanity.add_argument('--sweep', type=existing('file'), default=None,
                        help='drivers (default: config/reward_sanity.yaml)')
    renamed(sanity, '--variant', sanity.add_argument(
        '--reward-variant', action='append', default=[],
        help='reward variant of config/reward.yaml to score under (repeatable; default: env.yaml\'s)'))
    sanity.add_argument('--episodes', type=COUNT, default=30, help='paired seeds per driver')
    sanity.add_argument('--seed', type=SEED, default=SANITY_SEED, help='first seed (not a test or training seed)')
    sanity.add_argument('--jobs', type=COUNT, default=2, help='worker processes (one simulation each)')
    sanity.add_argument('--out', type=Path, default=Path('docs/results/reward_sanity'),
                        help='where reward_sanity.md and episodes.csv go')
    sanity.add_argument('--low-level', choices=['grid', 'options'], default='grid',
                        help='the drivers on the action grid, or off it with the options\' low level '
                             '(env.yaml options.low_level)')
    sanity.add_argument('--calibrate', action='store_true',
                        help='no simulation: search row-scale multipliers on --out\'s episodes.csv')
    sanity.set_defaults(func=cmd_reward_sanity)

    options = commands.add_parser('options-table', help='every constant option under every mode (the best '
                                                         'fixed driver per mode), with the references')
    config_options(options)
    options.add_argument('--episodes', type=COUNT, default=50, help='paired seeds per run')
    options.add_argument('--seed', type=SEED, default=VALIDATION_SEED,
                         help='first seed (900000: the validation seeds; 10000: the test seeds)')
    renamed(options, '--variant', options.add_argument(
        '--reward-variant', action='append', default=[],
        help='reward variant of config/reward.yaml to score under (repeatable; default: env.yaml\'s)'))
    options.add_argument('--policy', type=policy, action='append', default=[],
                         help='a policy (grid or options; repeatable): a directory name under policies/ or the path '
                              'of a policy directory or of a checkpoint, to judge against the best fixed driver of '
                              'each mode and SUMO\'s drivers on the same seeds; named by its run directory '
                              '(default: none, the fixed drivers only)')
    options.add_argument('--jobs', type=COUNT, default=2, help='worker processes (one simulation each)')
    options.add_argument('--out', type=Path, default=Path('docs/results/options'),
                         help='where constant_options.md and constant_options.csv go')
    options.set_defaults(func=cmd_options_table)

    tradeoff = commands.add_parser('tradeoff', help='a conditioned policy at every weight point (figure)')
    config_options(tradeoff)
    tradeoff.add_argument('--policy', type=policy, default=policy_path(Path('policies'), DEFAULT_ALGORITHM),
                          help='a mode-conditioned policy (grid or options): a directory name under policies/ or the '
                               'path of a policy directory or of a checkpoint')
    tradeoff.add_argument('--episodes', type=COUNT, default=20, help='seeds per weight point')
    tradeoff.add_argument('--seed', type=SEED, default=40_000, help='first seed (not a test or training seed)')
    tradeoff.add_argument('--out', type=Path, default=Path('docs/results/tradeoff'),
                          help='where tradeoff.csv and tradeoff.png go')
    tradeoff.add_argument('--plot-only', action='store_true',
                          help='only draw tradeoff.png again from --out\'s tradeoff.csv (no simulation, no checkpoint '
                               'read; --policy and --episodes name them in the title)')
    tradeoff.set_defaults(func=cmd_tradeoff)

    compare = commands.add_parser('compare', help='every method on every scenario variant (config/variants.yaml) on '
                                                  'the same seeds, as Ray tasks; a CSV per cell, reruns skip done cells')
    compare.add_argument('--config-dir', type=existing('dir'), default=None,
                         help='directory with scenario/graph/env/modes/reward YAML (default: config/)')
    compare.add_argument('--override', type=existing('file'), action='append', default=[],
                         help='YAML keyed by config file merged over the config of every variant (repeatable; '
                              'default: none)')
    renamed(compare, '--variants', compare.add_argument(
        '--scenario-variants', type=existing('file'), default=None,
        help='the scenario variants (default: <config dir>/variants.yaml)'))
    renamed(compare, '--variant', compare.add_argument(
        '--scenario-variant', action='append', default=[],
        help='only this cell of the scenario variants (repeatable; default: every cell)'))
    compare.add_argument('--method', type=comparison_method, action='append', default=[],
                         help='rule_based, sumo or a policy (a directory name under policies/ or the path of a policy '
                              'directory or of a checkpoint; repeatable; default: both drivers, and the shipped '
                              f'policies/{GRID_ALGORITHM}/policy.pt unless --train is given)')
    compare.add_argument('--train', action='append', default=[],
                         help='a method of config/training.yaml to train (repeatable; "all": every one) on the base '
                              'scenario, with the seeds and budget of --training; finished runs are reused '
                              '(default: none)')
    compare.add_argument('--training', type=existing('file'), default=None,
                         help='the training seeds and budget of --train (default: <config dir>/comparison.yaml)')
    compare.add_argument('--policies', type=Path, default=Path('policies/comparison'),
                         help='where each --train run trains and keeps its policy.pt (<policies>/<method>_s<seed>/, '
                              'beside its config.json and timing.json), reused when done with the same settings; '
                              'its logs are copied to <out>/training/ for the page (default: %(default)s, the runs '
                              'of docs/comparison.md)')
    compare.add_argument('--report-only', action='store_true',
                         help='only write the page from the CSVs and training logs in --out (no training, no '
                              'simulation, no checkpoint of a --train run read)')
    compare.add_argument('--report', type=Path, default=None,
                         help='the comparison page (figures beside it; default: <out>/comparison.md)')
    renamed(compare, '--mode', compare.add_argument(
        '--score-mode', action='append', default=[],
        help='score under this mode (repeatable; default: training.yaml conditioning.validation_modes)'))
    compare.add_argument('--episodes', type=number(int, 1), default=30, help='seeds per cell')
    compare.add_argument('--seed', type=SEED, default=TEST_SEED, help='first test seed (never used in training)')
    compare.add_argument('--out', type=Path, default=Path('runs/compare'),
                         help='where the CSVs go, one per cell (<out>/<variant>/<run>_<mode>.csv)')
    compare.add_argument('--address', default=None,
                         help='a Ray cluster to run on (its nodes need this package, SUMO and the policy files); '
                              'default: a local Ray on loopback')
    compare.add_argument('--workers', type=number(int, 1), default=None,
                         help='local Ray: simulations at once (default: every core)')
    compare.add_argument('--retries', type=number(int, 0), default=2, help='further attempts of a failed cell')
    compare.set_defaults(func=cmd_compare)

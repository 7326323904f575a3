"""Commands that run the scenario and evaluate: ``run`` (episodes of the scenario, the episode
metrics of ``exit_decision.episode_log``), ``evaluate`` (policies and the reference drivers on
fixed seeds) and ``one-step-gains`` (is there anything to improve on the prior?)."""
from __future__ import annotations

import argparse
from pathlib import Path

from tqdm import tqdm

from exit_decision.config.seeds import TEST_SEED
from exit_decision.cli.arguments import COUNT, SEED, OptionError, config_options, known, number, policy, renamed
from exit_decision.config import ConfigError, default_config_dir, load_project
from exit_decision.errors import UsageError


def cmd_run(args: argparse.Namespace) -> int:
    """Run episodes of the scenario and print the episode metrics (``exit_decision.episode_log``)."""
    from exit_decision.driving import fixed
    from exit_decision.driving.episode import play_episode
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.metrics import markdown_table, summarize

    if args.scenario_variant and args.scenario_override:
        raise UsageError('--scenario-variant and --scenario-override: give one (a variant is a scenario override)')
    if args.scenario_variant:
        from exit_decision.config import load_variants
        config = load_variants((args.config_dir or default_config_dir()) / 'variants.yaml', args.config_dir,
                               args.override, [args.scenario_variant])[args.scenario_variant]
    else:
        config = load_project(args.config_dir, args.scenario_override, args.override)
    if args.score_mode:
        known('--score-mode', args.score_mode, config.mode)
    env = ExitDecisionEnv(config, mode=args.score_mode, cav_driver='sumo' if args.driver == 'sumo' else 'policy')
    driver = fixed.sumo() if args.driver == 'sumo' else fixed.held_lanes(env)
    episodes, peak = [], 0
    try:
        for episode in tqdm(range(args.episodes), desc='episodes', unit='ep', disable=args.episodes == 1):
            episodes.append(play_episode(env, driver, args.seed + episode))
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


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate policies and/or the reference drivers on fixed seeds; print and save the table."""
    from exit_decision.evaluation.report import evaluate_runs

    config = load_project(args.config_dir, args.scenario_override, args.override)
    if not args.policy and not args.driver:
        raise OptionError('nothing to evaluate: give --policy or --driver (each repeatable)')
    for mode in args.score_mode:
        known('--score-mode', mode, config.mode)
    modes = args.score_mode or list(config.training.conditioning.validation_modes)
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


def reference_driver(text: str) -> str:
    """``sumo``, ``rule_based`` or ``rule_based:<name>`` (the name is checked against the sweep later)."""
    name, colon, variant = text.partition(':')
    if name == 'sumo' and not colon or name == 'rule_based' and (not colon or variant):
        return text
    raise argparse.ArgumentTypeError(f'{text!r}: expected sumo, rule_based or rule_based:<driver of reward_sanity.yaml>')


#: evaluate --help's examples
EVALUATE_EXAMPLES = '''examples:
  # the shipped policy against the neutral rule-based driver and SUMO's drivers, 20 test seeds, under CONP
  exit-decision evaluate --policy mdgqn_options_conditioned --driver rule_based --driver sumo --score-mode CONP --episodes 20 --out runs/evaluation_conp
  # the reference drivers alone under the validation modes, and each run's first 2 episodes drawn into runs/evaluation/show/
  exit-decision evaluate --driver rule_based --driver sumo --episodes 10 --show 2
  # the grid's conditioned MDGQN under the paper's four modes, 100 test seeds
  exit-decision evaluate --policy mdgqn_conditioned --driver rule_based --score-mode AGGI --score-mode AGGP --score-mode CONI --score-mode CONP --episodes 100 --out runs/evaluation
'''


def cmd_one_step_gains(args: argparse.Namespace) -> int:
    """One-step gains over the prior a policy carries, per scoring mode (``evaluation.one_step``)."""
    import numpy as np

    from exit_decision.driving.prior import PriorTable
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.one_step import fresh_future_gains, fresh_summary, one_step_gains, summary
    from exit_decision.model.modes import ModeWeights
    from exit_decision.model.policy import load_policy
    from exit_decision.tables import append_row

    config = load_project(args.config_dir, args.scenario_override, args.override)
    modes = args.score_mode or list(config.training.conditioning.validation_modes)
    for mode in modes:
        known('--score-mode', mode, config.mode)
    if args.reward_variant:
        known('--reward-variant', args.reward_variant, config.reward)
        config = config.model_copy(update={'env': config.env.model_copy(update={'reward_variant': args.reward_variant})})
    prior = load_policy(args.policy).prior
    if prior is None:
        raise UsageError(f'--policy {args.policy}: carries no prior (a policy over options trained since issue 39 does)')
    table, env = PriorTable.from_metadata(prior), ExitDecisionEnv(config)
    seeds, rng = [args.seed + i for i in range(args.episodes)], np.random.default_rng(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    print(f'one-step gains over the prior of {args.policy} (reward variant {env.reward_variant}; seeds {seeds[0]}..'
          f'{seeds[-1]}, {args.points} choice points each; rows in {args.out / "one_step_gains.csv"})')
    try:
        for mode in modes:
            bound = ModeWeights(config).mode(mode)
            rows = one_step_gains(env, table, bound, env.reward_fn.weights(config.mode(mode)), seeds, args.points, rng,
                                  desc=mode)
            for row in rows:
                append_row(args.out / 'one_step_gains.csv', {'mode': mode, **row})
            s = summary(rows)
            print(f'  {mode} (prior: {table.best_style(bound.weights)}): '
                  f'{s["points"]} points, {s["deviations"]} deviations, mean gain {s["mean_gain"]:+.4f}, '
                  f'{s["share_gaining"]:.0%} gain; best option per point {s["best_mean"]:+.4f} (median '
                  f'{s["best_median"]:+.4f}), above +0.05 at {s["best_above_0.05"]:.0%} of the points; the '
                  f'control (the prior\'s own option) within {s["control"]:.1e}')
            if args.futures:
                fresh = fresh_future_gains(env, table, bound, env.reward_fn.weights(config.mode(mode)), rows,
                                           args.futures, args.top, args.future_speed_sd, desc=f'{mode} futures')
                for row in fresh:
                    append_row(args.out / 'fresh_futures.csv', {'mode': mode, **row})
                f = fresh_summary(fresh)
                print(f'    on {args.futures} fresh futures (sd {args.future_speed_sd}): the best option per point '
                      f'gains {f["fresh_mean"]:+.4f} [{f["fresh_low"]:+.4f}, {f["fresh_high"]:+.4f}] (first look '
                      f'{f["first_mean"]:+.4f}; median over the points {f["fresh_median"]:+.4f}); resolved above 0 '
                      f'at {f["resolved_share"]:.0%} of {f["points"]} points; the prior\'s return moves '
                      f'{f["prior_spread"]:.3f} (sd) between futures')
    finally:
        env.close()
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Adds ``run``, ``evaluate`` and ``one-step-gains``."""
    run = commands.add_parser('run', help='run episodes of the scenario and print the metrics table')
    config_options(run)
    run.add_argument('--episodes', type=COUNT, default=1, help='number of episodes')
    run.add_argument('--seed', type=SEED, default=0, help='seed of the first episode, then +1 each')
    run.add_argument('--driver', choices=['sumo', 'hold'], default='sumo',
                     help='who drives the CAVs: sumo = SUMO\'s own drivers, routed to the target exit (the '
                          'rule-based reference); hold = the policy interface with SUMO\'s safety off, '
                          'every CAV holding lane and speed (shows that collisions are real)')
    renamed(run, '--mode', run.add_argument('--score-mode', default=None,
                                            help='the mode whose reward is reported (default: env.yaml\'s)'))
    renamed(run, '--variant', run.add_argument(
        '--scenario-variant', default=None,
        help='a cell of config/variants.yaml (e.g. density_1.45) instead of the base scenario; not with '
             '--scenario-override (default: the base scenario)'))
    run.add_argument('--csv', type=Path, default=None, help='write per-episode metrics here (default: not written)')
    run.add_argument('--markdown', type=Path, default=None,
                     help='write the table with the command and the full configuration here (default: not written)')
    run.set_defaults(func=cmd_run)

    evaluate = commands.add_parser('evaluate', help='evaluate policies / reference drivers on fixed seeds',
                                   epilog=EVALUATE_EXAMPLES)
    config_options(evaluate)
    evaluate.add_argument('--policy', type=policy, action='append', default=[],
                          help='a policy, grid or options: a directory name under policies/ or the path of a policy '
                               'directory or of a checkpoint (repeatable; default: none; give --policy, --driver or '
                               'both)')
    evaluate.add_argument('--driver', action='append', default=[], type=reference_driver,
                          help='a reference driver (repeatable): sumo (SUMO\'s own drivers), rule_based '
                               '(the neutral teacher, env.yaml\'s rule_based) or rule_based:<name> (a driver '
                               'of config/reward_sanity.yaml); default: none')
    renamed(evaluate, '--mode', evaluate.add_argument(
        '--score-mode', action='append', default=[],
        help='score (and run a conditioned policy) under this mode (repeatable; default: training.yaml '
             'conditioning.validation_modes); one CSV per run and mode'))
    evaluate.add_argument('--episodes', type=COUNT, default=50, help='test seeds: episodes per run')
    evaluate.add_argument('--seed', type=SEED, default=TEST_SEED, help='first test seed (never used in training)')
    evaluate.add_argument('--out', type=Path, default=Path('runs/evaluation'),
                          help='directory for the CSV and Markdown tables')
    evaluate.add_argument('--show', type=number(int, 0), default=0, metavar='N',
                          help='draw the first N episodes of each run into --out/show/: time-space diagram (PNG) '
                               'and bird\'s-eye clip (GIF; MP4 too where ffmpeg exists); 0: none; grid policies '
                               'and the drivers only')
    evaluate.set_defaults(func=cmd_evaluate)

    gains = commands.add_parser(
        'one-step-gains', help='how much one different option, once, gains over the prior a policy carries: is there '
                               'anything to improve on (docs/design.md, "The prior over options")')
    config_options(gains)
    gains.add_argument('--policy', type=policy, required=True,
                       help='a policy over options carrying its prior: a directory name under policies/ or the path of '
                            'a policy directory or of a checkpoint')
    gains.add_argument('--score-mode', action='append', default=None,
                       help='a mode to measure under (repeatable; default: the validation modes)')
    gains.add_argument('--episodes', type=COUNT, default=10, help='seeds')
    gains.add_argument('--seed', type=SEED, default=910_000, help='first seed (not a test or training seed)')
    gains.add_argument('--points', type=COUNT, default=3, help='random choice points per seed')
    gains.add_argument('--futures', type=number(int, 2), default=None, metavar='K',
                       help='measure each point\'s --top best options again on K fresh futures from the point, paired '
                            'with the prior on each: their real gain, not the maximum over one realisation\'s noise '
                            '(at least 2; default: not measured)')
    gains.add_argument('--top', type=COUNT, default=2, help='options per point measured on the fresh futures')
    gains.add_argument('--future-speed-sd', type=number(float, 0.0), default=0.02, metavar='SD',
                       help='a fresh future multiplies each human driver\'s hidden speed factor by 1 + N(0, SD) at the '
                            'point, and redraws the insertions to come')
    gains.add_argument('--reward-variant', default=None, help='a variant of config/reward.yaml (default: env.yaml\'s)')
    gains.add_argument('--out', type=Path, default=Path('runs/one_step_gains'),
                       help='where one_step_gains.csv goes (rows appended)')
    gains.set_defaults(func=cmd_one_step_gains)

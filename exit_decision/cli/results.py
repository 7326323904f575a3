"""The pages' inputs: ``plot`` (figures of training runs and evaluations) and ``report`` (the
results page)."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from exit_decision.cli.arguments import existing, policy_directory, renamed
from exit_decision.config import load_project
from exit_decision.model.names import DEFAULT_ALGORITHM


def cmd_plot(args: argparse.Namespace) -> int:
    """PNG figures from training runs and an evaluation directory."""
    from exit_decision.evaluation.plots import make_all
    from exit_decision.evaluation.statistics import MIN_LAST_THIRD_VALIDATIONS, last_third_slopes
    from exit_decision.tables import read_rows

    for path in make_all(args.policy, args.evaluation, args.out, args.one_step_gains):
        print(path)
    for run in args.policy or []:
        if (run / 'validation.csv').exists():
            print(f'{run}: the validation gain\'s slope over the last third of training, per 100 episodes [95%] '
                  f'(flattened: >= {MIN_LAST_THIRD_VALIDATIONS} validations there and the interval reaches 0 or below; '
                  f'falling: all of it below 0)')
            for mode, fit in last_third_slopes(read_rows(run / 'validation.csv')).items():
                print(f'  {mode}: {100 * fit["slope"]:+.3f} [{100 * fit["low"]:+.3f}, {100 * fit["high"]:+.3f}] from '
                      f'episode {fit["from_episode"]}, {fit["validations"]} validations: '
                      f'{"not flattened" if not fit["flat"] else "flattened, falling" if fit["high"] < 0 else "flattened"}')
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """Draw the shipped policy's training figures, write the results page from evaluation, ablation
    and figures, and the README's verdict and results table from the options table of the test seeds."""
    from exit_decision.evaluation.plots import make_all
    from exit_decision.evaluation.report import results_page, variant_links, write_readme_block, write_readme_table
    from exit_decision.experiments.constant_options import neutral_run, readme_table, readme_verdict
    from exit_decision.tables import read_rows

    config = load_project(args.config_dir)
    runs = args.policy or [Path('policies') / DEFAULT_ALGORITHM]
    shipped = next((run for run in runs if run.name == DEFAULT_ALGORITHM), Path('policies') / DEFAULT_ALGORITHM)
    drawn = make_all([shipped], None, args.figures)
    for path in drawn:
        print(path)
    if not drawn:   # e.g. an anchored policy, made by `exit-decision anchor` without a training log of its own
        print(f'{shipped}: no training log (training.csv, validation.csv); the shipped policy\'s figures in '
              f'{args.figures} are not drawn again', file=sys.stderr)
    print(results_page(args.evaluation, runs, args.sanity, args.tradeoff, args.figures, args.out,
                       max_steps=config.scenario.max_steps, speed_pairs=config.mode_matrix.speed_orderings,
                       options_dir=args.options_table))
    rows = read_rows(args.options_table / 'constant_options.csv')
    table = (rows, config.mode_matrix.modes, config.env.reward_variant, DEFAULT_ALGORITHM, neutral_run(config))
    links = variant_links(args.out, Path(os.path.relpath(args.out.resolve(), args.readme.resolve().parent)).as_posix())
    made_by = (args.options_table / 'constant_options.md').read_text(encoding='utf-8').split('`')[1]
    write_readme_block(args.readme, 'verdict', readme_verdict(*table))
    print(write_readme_table(args.readme, readme_table(*table, links=links), made_by))
    return 0


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Adds ``plot`` and ``report``."""
    plot = commands.add_parser('plot', help='PNG figures from training runs and evaluation results')
    renamed(plot, '--runs', plot.add_argument(
        '--policy', type=policy_directory, action='append', default=[],
        help='a training run: a directory name under policies/ or a run directory\'s path (repeatable; default: '
             'none)'), several=True)
    plot.add_argument('--evaluation', type=existing('dir'), default=None,
                      help='an evaluate --out directory (default: none)')
    plot.add_argument('--one-step-gains', type=existing('dir'), default=None, metavar='DIR',
                      help='a one-step-gains --futures --out directory: its best options\' first and fresh-future '
                           'gains (default: none)')
    plot.add_argument('--out', type=Path, default=Path('docs/figures'), help='where the figures go')
    plot.set_defaults(func=cmd_plot)

    report = commands.add_parser('report', help='write docs/results.md, the shipped policy\'s training figures and the README\'s '
                                   'verdict and results table from the generated results')
    report.add_argument('--evaluation', type=existing('dir'), default=Path('docs/results/evaluation'),
                        help='an evaluate --out directory (commands.txt and benchmarks.txt beside it)')
    report.add_argument('--config-dir', type=existing('dir'), default=None,
                        help='directory with scenario/graph/env/modes/reward YAML (default: config/)')
    renamed(report, '--runs', report.add_argument(
        '--policy', type=policy_directory, action='append', default=[],
        help='a training run (validation history, wall time): a directory name under policies/ or a run directory\'s '
             f'path (repeatable; default: policies/{DEFAULT_ALGORITHM})'), several=True)
    report.add_argument('--sanity', type=existing('dir'), default=Path('docs/results/reward_sanity_headway'),
                        help='a reward-sanity --out directory; the default holds the sweep under the frozen reward\'s '
                             'variant, headway')
    report.add_argument('--tradeoff', type=existing('dir'), default=Path('docs/results/tradeoff'),
                        help='a tradeoff --out directory')
    report.add_argument('--figures', type=existing('dir'), default=Path('docs/figures'),
                        help='the figures (a plot --out directory)')
    report.add_argument('--out', type=Path, default=Path('docs/results.md'), help='the results page to write')
    report.add_argument('--options-table', type=existing('dir'), default=Path('docs/results/options/test_seeds'),
                        help='an options-table --out directory of the test seeds, with --policy: the README\'s table')
    report.add_argument('--readme', type=existing('file'), default=Path('README.md'),
                        help='the README whose results table (between its markers) is written again')
    report.set_defaults(func=cmd_report)

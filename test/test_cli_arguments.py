"""Every command checks its options before it starts any work: a bad value (a count <= 0, a
negative seed or step, a file that does not exist or is no checkpoint, an unknown mode, method,
variant or driver) is one line naming it on stderr and exit code 2, never a traceback."""
import importlib
from pathlib import Path

import pytest

from exit_decision.cli import build_parser, main

REPO = Path(__file__).resolve().parent.parent
FIXTURE_BAG = str(REPO / 'test' / 'fixtures' / 'replay_bag' / 'bag')
NOT_CHECKPOINT = str(REPO / 'README.md')
A_POLICY = str(REPO / 'policies' / 'probes' / 'mdgqn_options_conditioned_traffic' / 'policy.pt')

#: what each command would start: none of it may run (replay and bag repair open the bag first:
#: that is where a bag that cannot be read is refused)
WORK = [('exit_decision.env', 'ExitDecisionEnv'), ('exit_decision.learning.trainer', 'Trainer'),
        ('exit_decision.evaluation.report', 'evaluate_runs'), ('exit_decision.evaluation.report', 'results_page'),
        ('exit_decision.ros.stack.launcher', 'run_stack'), ('exit_decision.ros.bags.replay', 'record_fixture'),
        ('exit_decision.ros.bags.show', 'show_bag'), ('exit_decision.experiments.ablation', 'run_ablation'),
        ('exit_decision.experiments.reward_sanity', 'write_sanity'),
        ('exit_decision.experiments.reward_sanity', 'calibrate'),
        ('exit_decision.experiments.tradeoff', 'run_tradeoff'),
        ('exit_decision.experiments.constant_options', 'write_table'),
        ('exit_decision.evaluation.plots', 'make_all'), ('exit_decision.experiments.compare', 'run_sweep'),
        ('exit_decision.experiments.compare', 'run_trainings'), ('exit_decision.benchmarks', 'bench_simulation'),
        ('exit_decision.benchmarks', 'bench_learning'), ('exit_decision.benchmarks', 'bench_sweep'),
        ('exit_decision.ros.stack.bench', 'bench_ros'), ('exit_decision.learning.anchoring', 'tune_anchor')]

# the bad value is the last argument; MISSING: a path that does not exist, EXISTING: one that does
BAD = [
    ['run', '--episodes', '0'], ['run', '--episodes', '-3'], ['run', '--seed', '-1'], ['run', '--mode', 'NOPE'],
    ['run', '--driver', 'nobody'], ['run', '--variant', 'NOPE'], ['run', '--config-dir', 'MISSING'],
    ['run', '--scenario-override', 'MISSING'], ['run', '--override', 'MISSING'],
    ['train', '--algorithm', 'NOPE'], ['train', '--mode', 'NOPE'], ['train', '--episodes', '0'],
    ['train', '--seed', '-1'], ['train', '--resume', NOT_CHECKPOINT], ['train', '--resume', 'MISSING'],
    ['train', '--init', NOT_CHECKPOINT], ['train', '--action-space', 'nope'], ['train', '--reward-variant', 'NOPE'],
    ['train', '--actors', '-1'],
    ['anchor', '--policy', 'MISSING'], ['anchor', '--policy', NOT_CHECKPOINT], ['anchor', '--kappa', '-1'],
    ['anchor', '--margin', 'x'], ['anchor', '--episodes', '0'], ['anchor', '--jobs', '0'],
    ['anchor', '--policy', A_POLICY, '--out', 'EXISTING', '--reward-variant', 'NOPE'],
    ['anchor', '--config-dir', 'MISSING'],
    ['evaluate', '--driver', 'rule_based', '--episodes', '0'],
    ['evaluate', '--driver', 'rule_based', '--episodes', '-3'],
    ['evaluate', '--seed', '-1'], ['evaluate', '--policy', NOT_CHECKPOINT], ['evaluate', '--policy', 'MISSING'],
    ['evaluate', '--driver', 'nobody'], ['evaluate', '--driver', 'rule_based', '--mode', 'NOPE'],
    ['evaluate', '--show', '-1'],
    ['stack', '--mode', 'NOPE'], ['stack', '--switch-to', 'NOPE'], ['stack', '--switch-at', '-5'],
    ['stack', '--switch-at', '1500'], ['stack', '--algorithm', 'NOPE'], ['stack', '--episodes', '-1'],
    ['stack', '--seed', '-1'], ['stack', '--bag', 'EXISTING'], ['stack', '--policy-dir', 'MISSING'],
    ['stack', '--config-dir', 'MISSING'], ['stack', '--compression', 'gzip'], ['stack', '--thread-priority', '100'],
    ['replay', 'MISSING'], ['replay', FIXTURE_BAG, '--mode', 'NOPE'], ['replay', FIXTURE_BAG, '--algorithm', 'NOPE'],
    ['replay', FIXTURE_BAG, '--policy', NOT_CHECKPOINT], ['replay', FIXTURE_BAG, '--policy-dir', 'MISSING'],
    ['bag', 'repair', 'MISSING'],
    ['show', 'MISSING'], ['show', FIXTURE_BAG, '--episode', '-1'], ['show', FIXTURE_BAG, '--start', '-1'],
    ['show', FIXTURE_BAG, '--end', '-1'], ['show', FIXTURE_BAG, '--speed', '0'], ['show', FIXTURE_BAG, '--fps', '0'],
    ['show', FIXTURE_BAG, '--config-dir', 'MISSING'],
    ['ablation', '--algorithm', 'NOPE'], ['ablation', '--mode', 'NOPE'], ['ablation', '--episodes', '0'],
    ['ablation', '--test-episodes', '0'], ['ablation', '--seed', '-1'], ['ablation', '--test-seed', '-1'],
    ['ablation', '--only', '99'], ['ablation', '--only', '-1'], ['ablation', '--config-dir', 'MISSING'],
    ['reward-sanity', '--sweep', 'MISSING'], ['reward-sanity', '--variant', 'NOPE'],
    ['reward-sanity', '--low-level', 'nope'], ['reward-sanity', '--episodes', '0'], ['reward-sanity', '--seed', '-1'], ['reward-sanity', '--jobs', '0'],
    ['options-table', '--episodes', '0'], ['options-table', '--seed', '-1'], ['options-table', '--jobs', '0'],
    ['options-table', '--config-dir', 'MISSING'], ['options-table', '--variant', 'NOPE'],
    ['options-table', '--policy', NOT_CHECKPOINT], ['options-table', '--policy', 'MISSING'],
    ['tradeoff', '--policy', NOT_CHECKPOINT], ['tradeoff', '--policy', 'MISSING'], ['tradeoff', '--episodes', '0'],
    ['tradeoff', '--seed', '-1'],
    ['plot', '--runs', 'MISSING'], ['plot', '--evaluation', 'MISSING'],
    ['report', '--evaluation', 'MISSING'], ['report', '--runs', 'MISSING'], ['report', '--sanity', 'MISSING'],
    ['report', '--config-dir', 'MISSING'], ['report', '--tradeoff', 'MISSING'], ['report', '--figures', 'MISSING'],
    ['report', '--options-table', 'MISSING'], ['report', '--readme', 'MISSING'],
    ['compare', '--method', 'nobody'], ['compare', '--method', NOT_CHECKPOINT], ['compare', '--variant', 'NOPE'],
    ['compare', '--variants', 'MISSING'], ['compare', '--train', 'NOPE'], ['compare', '--training', 'MISSING'],
    ['compare', '--mode', 'NOPE'], ['compare', '--episodes', '0'], ['compare', '--seed', '-1'],
    ['compare', '--workers', '0'], ['compare', '--retries', '-1'], ['compare', '--override', 'MISSING'],
    ['compare', '--config-dir', 'MISSING'],
    ['bench', 'nope'], ['bench', '--steps', '0'], ['bench', '--episodes', '0'], ['bench', '--seed', '-1'],
    ['bench', '--policy-dir', 'MISSING'], ['bench', '--thread-priority', '-1'],
]


@pytest.fixture
def no_work(monkeypatch):
    def started(*args, **kwargs):
        raise AssertionError('work started before the options were checked')
    for module, name in WORK:
        monkeypatch.setattr(importlib.import_module(module), name, started)


@pytest.mark.parametrize('argv', BAD, ids=[' '.join(Path(a).name if '/' in a else a for a in argv) for argv in BAD])
def test_a_bad_option_value_is_one_line_naming_it_and_exit_code_2(no_work, tmp_path, capsys, argv):
    argv = [str(tmp_path / 'missing') if a == 'MISSING' else str(tmp_path) if a == 'EXISTING' else a for a in argv]
    try:
        code = main(argv)
    except SystemExit as exit_:   # argparse's own refusal
        code = exit_.code
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and 'Traceback' not in err, err
    assert lines[0].startswith('exit-decision') and argv[-1] in lines[0], lines[0]
    assert not out


def test_evaluate_without_a_policy_or_driver_says_so_instead_of_an_empty_table(no_work, capsys):
    assert main(['evaluate']) == 2
    assert capsys.readouterr().err == ('exit-decision evaluate: error: nothing to evaluate: give --policy or --driver '
                                       '(each repeatable)\n')


#: options any text suits (where to write)
FREE = {'--out', '--csv', '--markdown', '--report', '--address', '--policies'}
#: the options every command with _common() has, checked through run's rows (the one definition)
COMMON = {'--config-dir', '--scenario-override', '--override'}


def test_every_option_that_takes_a_value_has_a_bad_one_in_the_table():
    """A new option that can take a bad value gets a row in BAD (or joins FREE if any text suits it)."""
    checked = {(argv[0], argv[-2]) for argv in BAD if argv[-2].startswith('--')}
    commands = build_parser()._subparsers._group_actions[0].choices
    for name, parser in commands.items():
        common = COMMON if {'--config-dir', '--scenario-override'} <= set(parser._option_string_actions) else set()
        taking = {action.option_strings[-1] for action in parser._actions
                  if action.option_strings and action.nargs != 0}
        unchecked = sorted(option for option in taking - FREE - common - {'--help'} if (name, option) not in checked)
        assert not unchecked, f'{name}: options with no bad value in BAD: {unchecked}'

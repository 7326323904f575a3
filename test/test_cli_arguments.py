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
        ('exit_decision.benchmarks', 'bench_learning'), ('exit_decision.benchmarks', 'bench_actors'),
        ('exit_decision.benchmarks', 'bench_sweep'),
        ('exit_decision.ros.stack.bench', 'bench_ros'), ('exit_decision.learning.anchoring', 'tune_anchor'),
        ('exit_decision.evaluation.one_step', 'one_step_gains')]

# the bad value is the last argument; MISSING: a path that does not exist, EXISTING: one that does
BAD = [
    ['run', '--episodes', '0'], ['run', '--episodes', '-3'], ['run', '--seed', '-1'], ['run', '--score-mode', 'NOPE'], ['run', '--mode', 'NOPE'],
    ['run', '--driver', 'nobody'], ['run', '--scenario-variant', 'NOPE'], ['run', '--variant', 'NOPE'], ['run', '--config-dir', 'MISSING'],
    ['run', '--scenario-override', 'MISSING'], ['run', '--override', 'MISSING'],
    ['train', '--algorithm', 'NOPE'], ['train', '--conditioning', 'NOPE'], ['train', '--mode', 'NOPE'], ['train', '--episodes', '0'],
    ['train', '--seed', '-1'], ['train', '--resume', NOT_CHECKPOINT], ['train', '--resume', 'MISSING'],
    ['train', '--init', NOT_CHECKPOINT], ['train', '--init', 'NOPE'], ['train', '--action-space', 'nope'], ['train', '--reward-variant', 'NOPE'],
    ['train', '--actors', '-1'],
    ['anchor', '--policy', 'MISSING'], ['anchor', '--policy', NOT_CHECKPOINT], ['anchor', '--kappa', '-1'],
    ['anchor', '--margin', 'x'], ['anchor', '--episodes', '0'], ['anchor', '--jobs', '0'],
    ['anchor', '--policy', A_POLICY, '--out', 'EXISTING', '--reward-variant', 'NOPE'],
    ['anchor', '--config-dir', 'MISSING'],
    ['one-step-gains', '--policy', 'MISSING'], ['one-step-gains', '--policy', A_POLICY, '--score-mode', 'NOPE'],
    ['one-step-gains', '--episodes', '0'], ['one-step-gains', '--seed', '-1'], ['one-step-gains', '--points', '0'],
    ['one-step-gains', '--futures', '1'], ['one-step-gains', '--top', '0'], ['one-step-gains', '--future-speed-sd', '-0.1'],
    ['one-step-gains', '--policy', A_POLICY, '--reward-variant', 'NOPE'], ['one-step-gains', '--config-dir', 'MISSING'],
    ['evaluate', '--driver', 'rule_based', '--episodes', '0'],
    ['evaluate', '--driver', 'rule_based', '--episodes', '-3'],
    ['evaluate', '--seed', '-1'], ['evaluate', '--policy', NOT_CHECKPOINT], ['evaluate', '--policy', 'MISSING'],
    ['evaluate', '--driver', 'nobody'], ['evaluate', '--driver', 'rule_based', '--score-mode', 'NOPE'],
    ['evaluate', '--driver', 'rule_based', '--mode', 'NOPE'], ['evaluate', '--policy', 'NOPE'],
    ['evaluate', '--show', '-1'],
    ['stack', '--start-mode', 'NOPE'], ['stack', '--mode', 'NOPE'], ['stack', '--switch-to', 'NOPE'], ['stack', '--switch-at', '-5'],
    ['stack', '--switch-at', '1500'], ['stack', '--policy', 'NOPE'], ['stack', '--policy', 'MISSING'], ['stack', '--policy', 'gqn'], ['stack', '--algorithm', 'NOPE'], ['stack', '--episodes', '-1'],
    ['stack', '--seed', '-1'], ['stack', '--bag', 'EXISTING'], ['stack', '--policy-dir', 'MISSING'], ['stack', '--policy-dir', 'EXISTING', '--policy', 'NOPE'],
    ['stack', '--config-dir', 'MISSING'], ['stack', '--compression', 'gzip'], ['stack', '--thread-priority', '100'],
    ['replay', 'MISSING'], ['replay', FIXTURE_BAG, '--mode', 'NOPE'], ['replay', FIXTURE_BAG, '--algorithm', 'NOPE'],
    ['replay', FIXTURE_BAG, '--policy', NOT_CHECKPOINT], ['replay', FIXTURE_BAG, '--policy-dir', 'MISSING'],
    ['bag', 'repair', 'MISSING'],
    ['show', 'MISSING'], ['show', FIXTURE_BAG, '--episode', '-1'], ['show', FIXTURE_BAG, '--start', '-1'],
    ['show', FIXTURE_BAG, '--end', '-1'], ['show', FIXTURE_BAG, '--speed', '0'], ['show', FIXTURE_BAG, '--fps', '0'],
    ['show', FIXTURE_BAG, '--config-dir', 'MISSING'],
    ['ablation', '--algorithm', 'NOPE'], ['ablation', '--score-mode', 'NOPE'], ['ablation', '--mode', 'NOPE'], ['ablation', '--episodes', '0'],
    ['ablation', '--test-episodes', '0'], ['ablation', '--seed', '-1'], ['ablation', '--test-seed', '-1'],
    ['ablation', '--only', '99'], ['ablation', '--only', '1', '99'], ['ablation', '--only', '-1'], ['ablation', '--config-dir', 'MISSING'],
    ['reward-sanity', '--sweep', 'MISSING'], ['reward-sanity', '--reward-variant', 'NOPE'], ['reward-sanity', '--variant', 'NOPE'],
    ['reward-sanity', '--low-level', 'nope'], ['reward-sanity', '--episodes', '0'], ['reward-sanity', '--seed', '-1'], ['reward-sanity', '--jobs', '0'],
    ['options-table', '--episodes', '0'], ['options-table', '--seed', '-1'], ['options-table', '--jobs', '0'],
    ['options-table', '--config-dir', 'MISSING'], ['options-table', '--reward-variant', 'NOPE'], ['options-table', '--variant', 'NOPE'],
    ['options-table', '--policy', NOT_CHECKPOINT], ['options-table', '--policy', 'MISSING'],
    ['tradeoff', '--policy', NOT_CHECKPOINT], ['tradeoff', '--policy', 'MISSING'], ['tradeoff', '--episodes', '0'],
    ['tradeoff', '--seed', '-1'],
    ['plot', '--policy', 'MISSING'], ['plot', '--runs', 'MISSING'], ['plot', '--runs', 'EXISTING', 'MISSING'], ['plot', '--evaluation', 'MISSING'], ['plot', '--one-step-gains', 'MISSING'],
    ['report', '--evaluation', 'MISSING'], ['report', '--policy', 'MISSING'], ['report', '--runs', 'MISSING'], ['report', '--sanity', 'MISSING'],
    ['report', '--config-dir', 'MISSING'], ['report', '--tradeoff', 'MISSING'], ['report', '--figures', 'MISSING'],
    ['report', '--options-table', 'MISSING'], ['report', '--readme', 'MISSING'],
    ['compare', '--method', 'nobody'], ['compare', '--method', NOT_CHECKPOINT], ['compare', '--scenario-variant', 'NOPE'], ['compare', '--variant', 'NOPE'],
    ['compare', '--scenario-variants', 'MISSING'], ['compare', '--variants', 'MISSING'], ['compare', '--train', 'NOPE'], ['compare', '--training', 'MISSING'],
    ['compare', '--score-mode', 'NOPE'], ['compare', '--mode', 'NOPE'], ['compare', '--episodes', '0'], ['compare', '--seed', '-1'],
    ['compare', '--workers', '0'], ['compare', '--retries', '-1'], ['compare', '--override', 'MISSING'],
    ['compare', '--config-dir', 'MISSING'],
    ['bench', 'nope'], ['bench', '--steps', '0'], ['bench', '--episodes', '0'], ['bench', '--seed', '-1'],
    ['bench', '--policy-dir', 'MISSING'], ['bench', '--thread-priority', '-1'],
    ['bench', '--phase-seconds', '0'], ['bench', '--pairs', '0'], ['bench', '--kind', 'huge'],
    ['bench', '--flooders', '0'], ['bench', '--huge-mb-per-s', '-1'], ['bench', 'flood', '--topic', '/nope'],
    ['bench', '--actors', '-1'], ['bench', '--actors', 'two'], ['bench', '--training-episodes', '0'],
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


#: (old spelling, new spelling): the same values, the old with a note (issue 41, one vocabulary)
RENAMED = [
    (['stack', '--mode', 'CONI'], ['stack', '--start-mode', 'CONI']),
    (['stack', '--algorithm', 'gqn'], ['stack', '--policy', 'gqn']),
    (['run', '--mode', 'CONI', '--variant', 'density_1.45'], ['run', '--score-mode', 'CONI', '--scenario-variant', 'density_1.45']),
    (['evaluate', '--mode', 'AGGP', '--mode', 'CONP'], ['evaluate', '--score-mode', 'AGGP', '--score-mode', 'CONP']),
    (['train', '--mode', 'CONP'], ['train', '--conditioning', 'CONP']),
    (['ablation', '--mode', 'CONP', '--only', '1', '2'], ['ablation', '--score-mode', 'CONP', '--only', '1', '--only', '2']),
    (['reward-sanity', '--variant', 'headway'], ['reward-sanity', '--reward-variant', 'headway']),
    (['options-table', '--variant', 'headway', '--variant', 'calibrated'],
     ['options-table', '--reward-variant', 'headway', '--reward-variant', 'calibrated']),
    (['compare', '--variant', 'base', '--variants', 'config/variants.yaml', '--mode', 'CONP'],
     ['compare', '--scenario-variant', 'base', '--scenario-variants', 'config/variants.yaml', '--score-mode', 'CONP']),
    (['report', '--runs', 'policies/mdgqn_conditioned', 'policies/gqn_options_conditioned'],
     ['report', '--policy', 'policies/mdgqn_conditioned', '--policy', 'policies/gqn_options_conditioned']),
    (['plot', '--runs', 'policies/mdgqn_conditioned', 'policies/gqn_options_conditioned'],
     ['plot', '--policy', 'policies/mdgqn_conditioned', '--policy', 'policies/gqn_options_conditioned']),
]


@pytest.mark.parametrize('old, new', RENAMED, ids=[' '.join(old) for old, _ in RENAMED])
def test_an_old_spelling_gives_what_the_new_one_gives_with_a_note(old, new, monkeypatch):
    monkeypatch.chdir(REPO)
    parsed_old, parsed_new = (vars(build_parser().parse_args(argv)) for argv in (old, new))
    notes = parsed_old.pop('notes')
    assert parsed_old == parsed_new and 'notes' not in parsed_new
    assert notes and all(' is now ' in text or 'once per value' in text for text in notes)


def test_a_policy_is_its_name_under_policies_or_a_path(monkeypatch):
    """evaluate, train (--init), options-table, tradeoff: the same checkpoint by its directory's
    name, its directory's path or its own path."""
    monkeypatch.chdir(REPO)
    checkpoint = (REPO / 'policies' / 'mdgqn_conditioned' / 'policy.pt').resolve()
    for given in ('mdgqn_conditioned', 'policies/mdgqn_conditioned', 'policies/mdgqn_conditioned/policy.pt'):
        for argv, dest in ((['evaluate', '--policy', given], 'policy'), (['train', '--init', given], 'init'),
                           (['options-table', '--policy', given], 'policy'), (['tradeoff', '--policy', given], 'policy')):
            value = getattr(build_parser().parse_args(argv), dest)
            assert (value[0] if isinstance(value, list) else value).resolve() == checkpoint, argv


def test_the_stack_takes_a_policy_by_name_or_path_and_the_old_algorithm_and_policy_dir():
    from exit_decision.cli.stack import stack_policy
    policies = REPO / 'policies'
    assert stack_policy(None, None) == (None, 'mdgqn_options_conditioned')
    assert stack_policy('mdgqn_conditioned', None) == (None, 'mdgqn_conditioned')
    assert stack_policy(str(policies / 'mdgqn_conditioned'), None) == (policies, 'mdgqn_conditioned')
    assert stack_policy(str(policies / 'mdgqn_conditioned' / 'policy.pt'), None) == (policies, 'mdgqn_conditioned')
    assert stack_policy('gqn', policies) == (policies, 'gqn'), 'a per-mode method: its <name>_<mode>/ directories'


def test_the_stack_takes_per_mode_policies_by_path_and_refuses_a_missing_mode_in_one_line(per_mode_policies, tmp_path,
                                                                                         no_work, capsys):
    """None ships: a per-mode method's policies are a directory's <method>_<mode>/ (issue 39)."""
    import shutil

    from exit_decision.cli.stack import stack_policy
    modes = ('AGGI', 'AGGP', 'CONI', 'CONP')
    for given in ('gqn', 'gqn_CONP', 'gqn_CONP/policy.pt'):
        assert stack_policy(str(per_mode_policies / given), None, modes) == (per_mode_policies, 'gqn'), given
    shutil.copytree(per_mode_policies / 'gqn_CONP', tmp_path / 'gqn_CONP')
    assert main(['stack', '--policy', str(tmp_path / 'gqn_CONP')]) == 2
    assert capsys.readouterr().err == (f"exit-decision stack: error: argument --policy: '{tmp_path}/gqn_CONP': no "
                                       f"{tmp_path}/gqn_AGGP/policy.pt; gqn needs one for each mode of the run "
                                       f"(AGGP, CONP)\n")


def test_an_old_spelling_notes_its_new_one_on_stderr_after_the_command(monkeypatch, capsys):
    import exit_decision.evaluation.plots as plots
    monkeypatch.setattr(plots, 'make_all', lambda runs, evaluation, out, gains: [f'{len(runs)} runs'])
    monkeypatch.chdir(REPO)
    assert main(['plot', '--runs', 'policies/mdgqn_conditioned', 'policies/gqn_options_conditioned', '--out', 'runs/never']) == 0
    out, err = capsys.readouterr()
    assert out.startswith('2 runs\n')
    assert err == 'exit-decision plot: note: --runs is now --policy; the old spelling still works, for now\n'

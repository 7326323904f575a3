"""Scenario variants (config/variants.yaml) and the compare sweep on a local Ray."""
import json
import re
import shutil

import pytest
import yaml

from exit_decision.cli import main
from exit_decision.config import ConfigError, default_config_dir, load_project
from exit_decision.config import load_variants
from exit_decision.experiments.compare import LOG_FILES, Job, SweepResult, run_on_ray
from exit_decision.scenario.sumo_inputs import network_sources, routes_source

HUMANS = ('HV1', 'HV2', 'HV3')


def _without(dump: dict, key: str) -> dict:
    return {k: v for k, v in dump.items() if k != key}


def test_each_variant_changes_only_its_factor_by_the_stated_amount():
    base = load_project().scenario
    variants = {name: config.scenario for name, config in load_variants(default_config_dir() / 'variants.yaml').items()}
    assert list(variants) == ['base', 'politeness_0.4', 'politeness_0', 'density_1.25', 'density_1.45',
                              'length_0.75', 'length_0.5']
    assert variants['base'] == base
    for value in (0.4, 0.0):
        scenario = variants[f'politeness_{value:g}']
        routes = routes_source(scenario)
        for name in HUMANS:
            assert re.search(rf'id="{name}"[^>]* lcCooperative="{value}"', routes)
        assert re.search(r'id="CAV"[^>]* lcCooperative="1.0"', routes)   # the method's own driver keeps 1
        assert _without(scenario.model_dump(), 'vehicle_types') == _without(base.model_dump(), 'vehicle_types')
    for factor in (1.25, 1.45):
        scenario = variants[f'density_{factor:g}']
        assert scenario.total_vehicles == round(base.total_vehicles * factor)
        for name, cls in scenario.vehicle_classes.items():
            assert abs(cls.count - base.vehicle_classes[name].count * factor) < 1
            assert cls.insertion_probability == pytest.approx(base.vehicle_classes[name].insertion_probability * factor)
        assert _without(scenario.model_dump(), 'vehicle_classes') == _without(base.model_dump(), 'vehicle_classes')
    for factor in (0.75, 0.5):
        scenario = variants[f'length_{factor:g}']
        edges = network_sources(scenario.road)['edg.xml']
        for edge, length in zip(('Highway_0', 'Highway_1', 'Highway_2'), base.road.highway_lengths):
            assert re.search(rf'id="{edge}"[^>]* length="{length * factor}"', edges)
        assert scenario.road.ramp_length == base.road.ramp_length
        assert _without(scenario.model_dump(), 'road') == _without(base.model_dump(), 'road')


def test_a_bad_key_in_a_cell_is_named_with_the_cell(tmp_path):
    path = tmp_path / 'variants.yaml'
    path.write_text(yaml.safe_dump({'cells': {'short': {'road': {'highway_length': [1.0, 2.0, 3.0]}}}}))
    with pytest.raises(ConfigError, match=r'(?s)cells\.short .*road\.highway_length'):
        load_variants(path)
    with pytest.raises(ConfigError, match=r"no cell 'long'"):
        load_variants(path, only=['long'])


#: 9 vehicles fit a 12-row graph; 40 do not, so every cell of ``overfull`` fails in its task
TINY = {'max_steps': 300, 'vehicle_classes': {'HV1': {'count': 3}, 'HV2': {'count': 2}, 'HV3': {'count': 1},
                                              'CAV': {'count': 3}}}
OVERFULL = {'vehicle_classes': {name: {'count': 10, 'insertion_probability': 0.5} for name in (*HUMANS, 'CAV')}}


def test_compare_writes_a_csv_per_cell_reports_a_failing_cell_and_a_rerun_skips_done_cells(tmp_path, capsys):
    variants, override, out = tmp_path / 'variants.yaml', tmp_path / 'graph.yaml', tmp_path / 'out'
    variants.write_text(yaml.safe_dump({'cells': {'tiny': TINY, 'overfull': OVERFULL}}))
    override.write_text(yaml.safe_dump({'graph': {'max_vehicles': 12}}))
    command = ['compare', '--scenario-variants', str(variants), '--override', str(override), '--method', 'rule_based',
               '--method', 'sumo', '--score-mode', 'AGGP', '--score-mode', 'CONP', '--episodes', '2', '--out', str(out),
               '--workers', '2', '--retries', '0']
    assert main(command) == 1
    printed = capsys.readouterr().out
    assert '4 cells: 2 run now, 0 already done (skipped), 2 failed' in printed
    assert re.search(r'failed: rule_based on overfull: GraphCapacityError: \d+ vehicles on the road but '
                     r'graph.max_vehicles = 12', printed)
    written = sorted(path.name for path in (out / 'tiny').glob('*.csv'))
    assert written == ['rule_based_AGGP.csv', 'rule_based_AGGP_actions.csv', 'rule_based_CONP.csv',
                       'rule_based_CONP_actions.csv', 'sumo_AGGP.csv', 'sumo_CONP.csv']
    for name in ('rule_based_AGGP.csv', 'sumo_CONP.csv'):
        seeds = [row.split(',')[0] for row in (out / 'tiny' / name).read_text().splitlines()[1:]]
        assert seeds == ['10000', '10001']
    assert not list((out / 'overfull').glob('*.csv'))
    stamps = {path: path.stat().st_mtime_ns for path in (out / 'tiny').iterdir()}

    assert main([*command, '--scenario-variant', 'tiny']) == 0
    assert '2 cells: 0 run now, 2 already done (skipped), 0 failed' in capsys.readouterr().out
    assert {path: path.stat().st_mtime_ns for path in (out / 'tiny').iterdir()} == stamps
    assert '## tiny' in (out / 'comparison.md').read_text()


def test_compare_trains_a_learned_method_on_a_budget_of_steps_and_reports_it_with_its_curve(tmp_path, capsys):
    variants, override, training, out = (tmp_path / name for name in ('variants.yaml', 'graph.yaml',
                                                                       'comparison.yaml', 'out'))
    variants.write_text(yaml.safe_dump({'cells': {'tiny': TINY}}))
    override.write_text(yaml.safe_dump({'graph': {'max_vehicles': 12}, 'scenario': TINY}))
    training.write_text(yaml.safe_dump({'training_mode': 'CONP', 'seeds': [0], 'budget': {
        'episodes': 50, 'environment_steps': 100, 'warmup_decisions': 10, 'replay_size': 2000, 'batch_size': 8,
        'demonstrations': {'episodes': 1, 'pretrain_updates': 20},
        'validation': {'every_episodes': 2, 'episodes': 1, 'parallel': False}}}))
    policies = tmp_path / 'policies'
    command = ['compare', '--scenario-variants', str(variants), '--override', str(override), '--train', 'dqn',
               '--training', str(training), '--score-mode', 'CONP', '--episodes', '2', '--out', str(out),
               '--policies', str(policies), '--workers', '2', '--retries', '0']
    assert main(command) == 0
    assert 'training: 1 training runs: 1 run now' in capsys.readouterr().out
    assert (policies / 'dqn_s0' / 'policy.pt').is_file()
    assert not list(out.rglob('*.pt')), 'the results keep no checkpoint'
    assert sorted(p.name for p in (out / 'training' / 'dqn_s0').iterdir()) == sorted(LOG_FILES)
    assert sorted(p.name for p in (out / 'tiny').glob('*_CONP.csv')) == ['dqn_s0_CONP.csv', 'rule_based_CONP.csv',
                                                                         'sumo_CONP.csv']
    page = (out / 'comparison.md').read_text()
    assert '| dqn |' in page and 'dqn > rule_based (learned > rule-based)' in page
    assert 'the same budget of environment steps (100 RL decisions a run' in page
    assert f'Made by `exit-decision compare --scenario-variants {variants} ' in page, 'the command as given, not pytest\'s'
    timing = json.loads((out / 'training' / 'dqn_s0' / 'timing.json').read_text())
    assert timing['decisions'] >= 100 and timing['episodes'] < 50, 'the steps budget ends the RL phase'
    assert (out / 'comparison_learning_curves.png').stat().st_size > 0
    assert main(command) == 0, 'a rerun reuses the trained run and the done cells'
    assert 'training: 1 training runs: 0 run now, 1 already done' in capsys.readouterr().out

    # the page again from the CSVs and logs alone: no checkpoint, no training, no simulation
    shutil.rmtree(policies)
    (out / 'comparison.md').unlink()
    assert main([*command, '--report-only']) == 0
    assert not policies.exists()
    assert (out / 'comparison.md').read_text() == page, 'the same page, made by the same command'


def _episodes(**columns):
    """Episode rows on test seeds 0..n-1 from per-metric value lists (other metrics 0)."""
    from exit_decision.experiments.comparison_report import TABLE_METRICS
    n = len(next(iter(columns.values())))
    return [{'seed': float(i), **dict.fromkeys(TABLE_METRICS, 0.0), **{k: float(v[i]) for k, v in columns.items()}}
            for i in range(n)]


def test_the_page_names_the_winner_of_a_metric_only_when_its_lead_over_the_runner_up_is_resolved():
    from exit_decision.experiments.comparison_report import winners_table
    runs = {'a': {'CONP': _episodes(reward=[10, 11, 12, 13], p_collision_CAV=[0.1, 0.0, 0.1, 0.0])},
            'b': {'CONP': _episodes(reward=[9, 10, 11, 12], p_collision_CAV=[0.0, 0.1, 0.0, 0.1])},
            'c': {'CONP': _episodes(reward=[1, 2, 3, 4], p_collision_CAV=[0.5, 0.5, 0.5, 0.5])}}
    rows = {line.split(' | ')[0].strip('| '): line for line in winners_table(runs, 'CONP').splitlines()}
    assert '| a | 11.5 | b | +1 [+1, +1] | wins |' in rows['reward (higher)']
    # a and b collide equally often, on other seeds: tied, whichever is listed best
    assert 'tied with the runner-up' in rows['p_collision_CAV (lower)']
    assert '| c |' not in rows['p_collision_CAV (lower)']


def test_a_drop_under_a_variant_is_paired_by_test_seed_and_marked_when_resolved():
    from exit_decision.experiments.comparison_report import drop_table
    base = _episodes(reward=[10, 20, 30], p_CAV=[1, 1, 1])
    per_variant = {'base': {'m': {'CONP': base}},
                   'hard': {'m': {'CONP': _episodes(reward=[8, 18, 28], p_CAV=[1, 0.5, 1])}}}
    row = drop_table(per_variant, 'base', 'CONP').splitlines()[-1]
    # return: -2 on every seed (resolved although the seeds' returns spread 10..30); p_CAV: unresolved
    assert row.startswith('| m | -0.167 [')
    assert '/ -2 [-2, -2]*' in row
    assert not row.split(' / ')[0].endswith('*')


def test_run_on_a_variant_says_its_peak_of_vehicles_against_the_graphs_capacity(capsys):
    assert main(['run', '--scenario-variant', 'length_0.5', '--episodes', '1', '--seed', '10000']) == 0
    peak = int(re.search(r'peak vehicles on the road at one step: (\d+) \(the graph holds N = 60\)',
                         capsys.readouterr().out).group(1))
    assert 0 < peak <= 60
    assert main(['run', '--scenario-variant', 'length_0.1']) != 0
    assert "no cell 'length_0.1'; cells: base, politeness_0.4" in capsys.readouterr().err


def test_a_claim_says_how_far_its_training_runs_spread_and_when_they_disagree():
    from exit_decision.experiments.comparison_report import claim_lines
    runs = {'sgrl': {'CONP': _episodes(reward=[3, 4, 5])}, 'mgrl': {'CONP': _episodes(reward=[1, 2, 3])}}
    (line,) = [line for line in claim_lines(runs, 'CONP', {'sgrl': 3, 'mgrl': 3},
                                            {'sgrl': [2.0, 6.0, 4.0], 'mgrl': [1.0, 3.0, 2.0]})
               if line.startswith('- SGRL > MGRL')]
    # averaged over the runs SGRL leads by 2 on every test seed; single runs range from 2 - 3 to 6 - 1
    assert 'return difference +2.000 [+2.000, +2.000]; training runs: -1.000 to +5.000 (they disagree in sign)' in line
    assert line.endswith('**holds**')


def test_a_task_that_raises_once_is_retried_in_a_new_worker_and_counts_as_done(tmp_path):
    marker = tmp_path / 'attempted'

    def raises_the_first_time(path: str) -> tuple[int, int]:   # nested: Ray ships it by value
        import os
        from pathlib import Path
        if not Path(path).exists():
            Path(path).write_text(str(os.getpid()))
            raise RuntimeError('the first attempt fails')
        return int(Path(path).read_text()), os.getpid()

    got = []
    job = Job('flaky', raises_the_first_time, (str(marker),), got.append)
    result = run_on_ray([job], SweepResult(cells=1), None, 1, 1, False)
    assert (result.done, result.failed, len(got)) == (1, {}, 1)
    first, second = got[0]
    assert first != second, 'the second attempt ran in another worker process'
    marker.unlink()
    result = run_on_ray([job], SweepResult(cells=1), None, 1, 0, False)
    assert result.done == 0 and 'the first attempt fails' in result.failed['flaky']

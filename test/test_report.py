"""The results page's target and ordering checks on hand-made numbers."""
import json

from exit_decision.config import load_project
from exit_decision.evaluation.report import demonstrator_headway, step_cap_lines, target_checks


def runs(**values):
    table = {}
    for run, (v, p_cav, collisions) in values.items():
        table[run] = {'v_AVs': (v, 0.0), 'p_CAV': (p_cav, 0.0), 'p_collision_CAV': (collisions, 0.0)}
    return table


def test_targets_and_orderings_are_checked_on_the_numbers():
    lines = target_checks(runs(
        mdgqn_AGGI=(17.0, 0.97, 0.0), mdgqn_AGGP=(16.5, 0.96, 0.005),
        mdgqn_CONI=(16.0, 0.93, 0.0), mdgqn_CONP=(16.8, 0.99, 0.02),
        gqn_AGGI=(16.0, 0.90, 0.0), sumo=(15.7, 1.0, 0.0)))
    text = '\n'.join(lines)
    assert 'MDGQN AGGI: p_collision_CAV 0.0000 (target <= 0.01), p_CAV 0.970 (target >= 0.95): met' in text
    assert 'MDGQN CONI: p_collision_CAV 0.0000 (target <= 0.01), p_CAV 0.930 (target >= 0.95): NOT met' in text
    assert 'short by 0.0000 collisions, 0.020 p_CAV' in text
    assert 'MDGQN: AGGI faster than CONI (17.00 vs 16.00 m/s): holds' in text
    assert 'MDGQN: AGGP faster than CONP (16.50 vs 16.80 m/s): does not hold' in text
    assert 'AGGI: MDGQN at least as good as GQN' in text and 'holds' in text
    assert 'faster than the SUMO reference (15.70 m/s) at p_collision_CAV <= 0.01: holds (mdgqn_AGGI, mdgqn_AGGP, gqn_AGGI)' in text


def test_a_policy_line_names_the_demonstrator_its_mode_learned_from(tmp_path):
    config = load_project(overrides=[{'env': {'rule_based': {'time_headway': 1.2}},
                                      'modes': {'modes': {'AGGI': {'rule_based': {'time_headway': 1.0}},
                                                          'CONP': {'rule_based': {}}}}}]).model_dump(mode='json')
    for mode, expected in (('AGGI', '1'), ('CONP', '1.2')):
        path = tmp_path / f'{mode}.json'
        path.write_text(json.dumps({'mode': mode, 'config': config}))
        assert demonstrator_headway(path) == f'; demonstrator headway {expected} s'
    assert demonstrator_headway(tmp_path / 'missing.json') == ''


def test_episodes_cut_by_the_step_cap_are_counted_per_run(tmp_path):
    from exit_decision.tables import write_rows
    write_rows(tmp_path / 'mdgqn_AGGI.csv', [{'steps': 1500.0}, {'steps': 800.0}, {'steps': 1500.0}])
    write_rows(tmp_path / 'sumo.csv', [{'steps': 820.0}])
    write_rows(tmp_path / 'mdgqn_AGGI_actions.csv', [{'steps': 1500.0}])
    assert step_cap_lines(tmp_path, 1500) == ['- mdgqn_AGGI: 2 of 3 episodes ran into the 1500-step cap']
    assert step_cap_lines(tmp_path, 2000) == ['- none: no episode ran into the 2000-step cap']

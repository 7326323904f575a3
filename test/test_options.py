"""The options action space: masks from the road and the planner only, when options end, and
the rule-based low level that executes them under the shield."""
import numpy as np
import pytest

from exit_decision.actions import ActionGrid
from exit_decision.agents.lane_planner import LanePlanner
from exit_decision.agents.options import OptionExecutor, OptionSpace
from exit_decision.agents.shield import Shield
from exit_decision.config import load_project
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import TrafficSnapshot

from conftest import make_vehicle


def space_of(config):
    geometry = RoadGeometry.of(config.scenario.road)
    shield = Shield.of(config, ActionGrid(config.env.actions), geometry)
    return OptionSpace(config, shield, LanePlanner.of(config, shield))


@pytest.fixture(scope='module')
def space(project_config):
    return space_of(project_config)


def intents(space, mask):
    return {space.options[i].lane_intent for i in np.flatnonzero(mask)}


def test_masks_follow_the_road_and_the_route(space):
    middle = make_vehicle('m', 'CAV', lane=1, position=60.0)           # before Exit_0: lanes 1-2 are the route
    assert intents(space, space.mask(middle)) == {'keep', 'left', 'route'}, 'right would be lane 0: the first exit'
    top = make_vehicle('t', 'CAV', lane=2, position=60.0)
    assert intents(space, space.mask(top)) == {'keep', 'right', 'route'}, 'no lane 3'
    off_route = make_vehicle('o', 'CAV', lane=1, position=250.0, edge='Highway_1')   # lane 0 is the route
    assert space.planned(off_route)
    assert intents(space, space.mask(off_route)) == {'route'}, 'the planner owns its lane, near an exit: route'
    # every style is offered with every allowed intent
    assert space.mask(middle).sum() == 3 * len(space.drivers)


def test_near_the_first_exit_a_cav_not_in_the_lane_it_needs_follows_the_route(space):
    start = space.geometry.first_exit.merge_done_at - space.route_only_before
    assert space.route_only_before > 0
    early = make_vehicle('e', 'CAV', lane=2, position=start - 5.0)
    assert intents(space, space.mask(early)) == {'keep', 'right', 'route'}
    late = make_vehicle('l', 'CAV', lane=2, position=start + 5.0)
    assert intents(space, space.mask(late)) == {'route'}, 'lane 2 must reach lane 1 before the first exit'
    ready = make_vehicle('r', 'CAV', lane=1, position=start + 5.0)
    assert intents(space, space.mask(ready)) == {'keep', 'left', 'route'}, 'lane 1 is where it must be'
    exit_lane = make_vehicle('x', 'CAV', lane=0, position=300.0, edge='Highway_1')
    assert intents(space, space.mask(exit_lane)) == {'keep', 'route'}


def test_a_cav_the_planner_drives_keeps_the_planners_style(space):
    off_route = make_vehicle('o', 'CAV', lane=1, position=250.0, edge='Highway_1', speed=20.0)
    leader = make_vehicle('a', 'HV1', lane=1, position=275.0, edge='Highway_1', speed=15.0)
    snapshot = TrafficSnapshot([off_route, leader])
    executor = OptionExecutor(space)
    commands = {}
    for style in ('calm', space.planner_style):
        executor.reset()
        executor.choose(snapshot, ['o'], 0.0, lambda vehicle, mask: space.index('route', style))
        commands[style] = executor.commands(snapshot, ['o'])['o']
    assert commands['calm'] == commands[space.planner_style]


def test_masks_are_the_same_under_every_mode(project_config):
    vehicles = [make_vehicle(f'c{i}', 'CAV', lane=lane, position=position, edge=edge)
                for i, (lane, position, edge) in enumerate([(0, 30.0, 'Highway_0'), (1, 60.0, 'Highway_0'),
                                                            (2, 120.0, 'Highway_0'), (1, 250.0, 'Highway_1'),
                                                            (0, 300.0, 'Highway_1'), (2, 450.0, 'Highway_2')])]
    masks = {}
    for mode in project_config.modes:
        space = space_of(load_project(overrides=[{'env': {'mode': mode}}]))
        masks[mode] = np.array([space.mask(v) for v in vehicles])
    first = next(iter(masks.values()))
    assert all((m == first).all() for m in masks.values())


def test_an_option_ends_on_time_when_its_change_is_done_at_a_takeover_or_a_reset(space):
    executor = OptionExecutor(space)
    cav = make_vehicle('c', 'CAV', lane=1, position=30.0)
    snapshot = TrafficSnapshot([cav])
    left = space.index('left', 'neutral')
    chosen = []

    def chooser(vehicle, mask):
        chosen.append(vehicle.vehicle_id)
        return left if mask[left] else space.index('keep', 'neutral')

    assert executor.choose(snapshot, ['c'], 0.0, chooser) == {'c': left}
    executor.choose(snapshot, ['c'], 0.5, chooser)
    assert len(chosen) == 1, 'held, not chosen again'
    changed = make_vehicle('c', 'CAV', lane=2, position=40.0)
    executor.choose(TrafficSnapshot([changed]), ['c'], 1.0, chooser)
    assert len(chosen) == 2, 'its lane change is done'
    executor.choose(TrafficSnapshot([changed]), ['c'], 1.0 + space.hold_time, lambda v, m: space.index('keep', 'calm'))
    assert executor.held['c'].index == space.index('keep', 'calm'), 'its hold time is over'
    off_route = make_vehicle('c', 'CAV', lane=1, position=250.0, edge='Highway_1')
    executor.choose(TrafficSnapshot([off_route]), ['c'], 1.5 + space.hold_time, lambda v, m: space.index('route', 'close'))
    assert executor.held['c'].index == space.index('route', 'close'), 'the planner took it over'
    executor.reset()
    assert executor.held == {}
    with pytest.raises(ValueError, match='masked'):
        executor.choose(TrafficSnapshot([off_route]), ['c'], 9.0, lambda v, m: left)


def test_the_low_level_executes_the_intent_and_the_style(space):
    executor = OptionExecutor(space)
    cav = make_vehicle('c', 'CAV', lane=1, position=60.0, speed=20.0)
    snapshot = TrafficSnapshot([cav])
    executor.choose(snapshot, ['c'], 0.0, lambda v, m: space.index('left', 'neutral'))
    assert executor.commands(snapshot, ['c'])['c'].lane_change == 1
    executor.reset()
    executor.choose(snapshot, ['c'], 0.0, lambda v, m: space.index('keep', 'neutral'))
    assert executor.commands(snapshot, ['c'])['c'].lane_change == 0
    top = make_vehicle('c', 'CAV', lane=2, position=60.0, speed=20.0)
    executor.reset()
    executor.choose(TrafficSnapshot([top]), ['c'], 0.0, lambda v, m: space.index('route', 'neutral'))
    assert executor.commands(TrafficSnapshot([top]), ['c'])['c'].lane_change == -1, 'the route plan: lane 1'

    leader = make_vehicle('l', 'HV1', lane=1, position=100.0, speed=20.0)   # 35 m at equal speed
    snapshot = TrafficSnapshot([cav, leader])
    accelerations = {}
    for style in ('close', 'calm'):
        executor.reset()
        executor.choose(snapshot, ['c'], 0.0, lambda v, m: space.index('keep', style))
        accelerations[style] = executor.commands(snapshot, ['c'])['c'].acceleration
    assert accelerations['close'] > 0 > accelerations['calm'], 'a 0.8 s style closes in, a 2 s one drops back'


def test_unknown_style_keys_are_refused_at_load(tmp_path):
    import shutil
    from exit_decision.config import ConfigError, default_config_dir, load_yaml
    import yaml
    config_dir = tmp_path / 'config'
    shutil.copytree(default_config_dir(), config_dir)
    env = load_yaml(config_dir / 'env.yaml')
    env['options']['styles']['fast'] = {'headway': 0.5}
    (config_dir / 'env.yaml').write_text(yaml.safe_dump(env))
    with pytest.raises(ConfigError, match="styles.fast: unknown rule_based key 'headway'"):
        load_project(config_dir)


def test_a_constant_option_drives_a_whole_episode_to_the_target_exit(project_config):
    """The env, the executor and the low level together: the neutral style on the route's lane
    plan, one real episode; the commands are off the grid."""
    from exit_decision.driving.episode import play_episode
    from exit_decision.driving.fixed import constant_option
    from exit_decision.env import ExitDecisionEnv

    env = ExitDecisionEnv(project_config)
    try:
        driver = constant_option(OptionSpace(project_config, env.shield, env.planner), 'neutral')
        executor = driver.executor
        accelerations = []
        commands = executor.commands

        def recorded(snapshot, cav_ids):
            result = commands(snapshot, cav_ids)
            accelerations.extend(c.acceleration for c in result.values())
            return result

        executor.commands = recorded
        metrics = play_episode(env, driver, 10)
    finally:
        env.close()
    assert metrics['p_CAV'] == 1.0 and metrics['p_collision_CAV'] == 0.0
    off_grid = [a for a in accelerations if abs(a * 2 - round(a * 2)) > 1e-6]
    assert len(off_grid) > len(accelerations) / 2


def test_the_best_fixed_driver_is_the_best_constant_option_per_mode():
    from exit_decision.experiments.constant_options import table_markdown

    def row(run, seed, aggi, coni):
        return {'run': run, 'seed': seed, 'variant': 'v', 'return_AGGI': aggi, 'return_CONI': coni,
                **dict.fromkeys(('v_AVs', 'headway_CAV', 'N_braking_CAV', 'N_braking', 'p_CAV', 'p_collision_CAV'), 1.0)}
    rows = [row(run, seed, aggi + seed, coni + seed) for seed in (1, 2, 3)
            for run, aggi, coni in [('option_neutral', 10, 10), ('option_close', 11, 9), ('option_calm', 8, 12),
                                    ('sumo', 20, 20)]]
    text = table_markdown(rows, ['AGGI', 'CONI'], 'v', 'option_neutral')
    assert "AGGI `option_close`" in text and "CONI `option_calm`" in text, 'references are not fixed options'
    assert '+1.000 [+1.000, +1.000] ↑' in text


def _readme_rows(collisions: float = 0.0):
    """Three seeds of the fixed drivers and a policy 'shipped' (its CAV collisions under CONI given)."""
    def row(run, seed, aggi, coni, speed=15.0):
        return {'run': run, 'seed': seed, 'variant': 'v', 'return_AGGI': aggi, 'return_CONI': coni, 'v_AVs': speed,
                'N_braking': 5.0 + seed + (2.0 if '@' in run else 0.0), 'p_collision_CAV': 0.0,
                **dict.fromkeys(('headway_CAV', 'N_braking_CAV', 'p_CAV'), 1.0)}
    rows = [row(run, seed, aggi + seed * seed, coni + seed, speed) for seed in (1, 2, 3)
            for run, aggi, coni, speed in [('option_neutral', 10, 10, 15), ('option_close', 11, 9, 16),
                                           ('option_calm', 8, 12, 14), ('sumo', 9, 9, 15),
                                           ('shipped@AGGI', 12, 0, 17), ('shipped@CONI', 0, 11, 13)]]
    for r in rows:
        r['p_collision_CAV'] = collisions if r['run'] == 'shipped@CONI' else 0.0
    return rows


def test_the_readme_table_puts_the_policy_beside_the_best_fixed_neutral_and_sumo_drivers_per_mode():
    from exit_decision.experiments.constant_options import readme_table

    rows = _readme_rows()
    lines = readme_table(rows, ['AGGI', 'CONI'], 'v', 'shipped', 'option_neutral', links={'v': 'docs/r.md#v'}).splitlines()
    assert "hard brakings per episode, the CAVs' own | hard brakings per episode, all vehicles |" in lines[0]
    assert lines[0].endswith('| return − the neutral driver [95%] | return − the best fixed driver [95%] |')
    aggi = [line for line in lines if line.startswith('| AGGI |')]
    assert [line.split(' | ')[1] for line in aggi] == [
        'the shipped policy', 'the best fixed driver (`close`)', 'the neutral driver', "SUMO's drivers"]
    assert '| 17.00 |' in aggi[0] and aggi[0].endswith('+2.000 [+2.000, +2.000] ↑ | +1.000 [+1.000, +1.000] ↑ |')
    assert aggi[1].endswith('↑ | — |') and aggi[2].endswith('— | -1.000 [-1.000, -1.000] ↓ |')
    coni = [line for line in lines if line.startswith('| CONI |')]
    assert 'the best fixed driver (`calm`)' in coni[1] and coni[3].endswith('-1.000 [-1.000, -1.000] ↓ | -3.000 [-3.000, -3.000] ↓ |')
    assert '- [`v`](docs/r.md#v) (this table): config/reward.yaml' in lines
    no_policy = readme_table([r for r in rows if '@' not in r['run']], ['AGGI'], 'v', 'shipped', 'option_neutral')
    assert [line.split(' | ')[1] for line in no_policy.splitlines() if line.startswith('| AGGI')] == [
        'the best fixed driver (`close`)', 'the neutral driver', "SUMO's drivers"]


def test_the_readme_verdict_says_safely_only_while_the_policy_collides_no_more_than_the_best_fixed_driver():
    from exit_decision.experiments.constant_options import readme_verdict

    safe = readme_verdict(_readme_rows(), ['AGGI', 'CONI'], 'v', 'shipped', 'option_neutral')
    assert 'safely' in safe and 'Not safer' not in safe
    assert 'Against the best fixed driver: above under AGGI; below under CONI.' in safe
    assert "Against SUMO's drivers: above under AGGI, CONI." in safe
    assert 'more under AGGI, CONI (AGGI +2.00 [+2.00, +2.00] ↑; CONI +2.00 [+2.00, +2.00] ↑)' in safe
    unsafe = readme_verdict(_readme_rows(collisions=0.01), ['AGGI', 'CONI'], 'v', 'shipped', 'option_neutral')
    assert 'safe' not in unsafe.replace('Not safer', '')
    assert 'more CAV collisions than the best fixed driver under CONI' in unsafe
    assert 'AGGI 0.0000 against 0.0000, CONI 0.0100 against 0.0000' in unsafe
    assert 'No policy' in readme_verdict([r for r in _readme_rows() if '@' not in r['run']], ['AGGI'], 'v', 'shipped',
                                         'option_neutral')


def test_the_readme_links_each_reward_variant_to_its_table_in_the_options_section(tmp_path):
    from exit_decision.evaluation.report import OPTIONS_HEADING, variant_links

    page = tmp_path / 'results.md'
    page.write_text('# Results\n\n```\n# a comment\n```\n\n## The reward\n\n### Reward variant `headway` (100 seeds)\n\n'
                    f'{OPTIONS_HEADING}\n\n### Reward variant `headway` (100 seeds)\n\n'
                    '### Reward variant `calibrated` (100 seeds)\n\n## Ablation\n\n### Reward variant `calibrated` (100 seeds)\n')
    assert variant_links(page, 'docs/results.md') == {'headway': 'docs/results.md#reward-variant-headway-100-seeds-1',
                                                      'calibrated': 'docs/results.md#reward-variant-calibrated-100-seeds'}


def test_the_env_over_options_reads_only_the_choosing_rows(project_config):
    from exit_decision.env import ExitDecisionEnv

    env = ExitDecisionEnv(project_config, action_space='options')
    try:
        space = env.options
        assert env.action_space.nvec[0] == space.size
        _, info = env.reset(seed=3)
        route = space.index('route', 'neutral')

        def planned(row):
            return space.planned(env.sim.snapshot.by_id[env.graph.vehicle_ids[row]])

        checked = 0
        for _ in range(100):                               # held for the hold time, once begun
            rows = np.flatnonzero(info['choosing'])
            assert info['option_masks'][rows, route].all()
            before = {env.graph.vehicle_ids[row]: planned(row) for row in rows}
            _, _, _, _, info = env.step(np.full(env.graph.num_nodes, route))
            row_of = env.graph.row_of()
            kept = [row_of[v] for v, was in before.items() if v in row_of and planned(row_of[v]) == was]
            assert (info['options'][kept] == route).all() and not info['choosing'][kept].any()
            checked += len(kept)
            if checked >= 5:
                break
        assert checked >= 5
        rows = np.flatnonzero(info['options'] == route)
        rows = rows[~info['choosing'][rows]]
        # rows that do not choose are not read: a value that is no option changes nothing there
        ignored = np.full(env.graph.num_nodes, route)
        ignored[rows] = 10 ** 6
        _, _, _, _, info = env.step(ignored)
        assert (info['options'][rows] == route).all()
        # a masked option for a choosing row is refused
        while not info['choosing'].any():
            _, _, _, _, info = env.step(np.full(env.graph.num_nodes, route))
        chooser = np.flatnonzero(info['choosing'])[0]
        masked = np.flatnonzero(~info['option_masks'][chooser])
        if masked.size:
            action = np.full(env.graph.num_nodes, route)
            action[chooser] = masked[0]
            with pytest.raises(ValueError, match='masked'):
                env.step(action)
    finally:
        env.close()


def test_report_writes_the_readme_table_between_its_markers_and_refuses_a_readme_without_them(tmp_path):
    from exit_decision.errors import UsageError
    from exit_decision.evaluation.report import README_MARKERS, write_readme_table

    readme = tmp_path / 'README.md'
    readme.write_text(f'# title\n\n{README_MARKERS[0]}\nold table\n{README_MARKERS[1]}\n\n## next\n')
    write_readme_table(readme, '| new |', 'exit-decision options-table --seed 10000')
    write_readme_table(readme, '| newer |', 'exit-decision options-table --seed 10000')
    assert readme.read_text() == (f'# title\n\n{README_MARKERS[0]}\n| newer |\nRows made by '
                                  f'`exit-decision options-table --seed 10000`.\n{README_MARKERS[1]}\n\n## next\n')
    readme.write_text('# no markers\n')
    with pytest.raises(UsageError, match='README.md: needs the lines'):
        write_readme_table(readme, '| new |', 'x')


def test_a_policy_driver_over_options_runs_the_network_only_when_a_cav_begins_an_option(tmp_path):
    from exit_decision.config import default_config_dir
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.driving.policy import policy_driver
    from exit_decision.model.modes import ModeWeights
    from exit_decision.model.policy import load_controller
    from ros_helpers import random_policies

    config = load_project()
    policy = random_policies(default_config_dir(), tmp_path, modes=()) / 'mdgqn_options_conditioned' / 'policy.pt'
    env = ExitDecisionEnv(config, action_space='options')
    try:
        env.reset(seed=5)
        route = env.options.index('route', 'neutral')
        while not env.graph.cav_ids():
            env.step(np.full(env.graph.num_nodes, route))
        controller = load_controller(config, policy, env.shield, env.planner, action_spaces=('options',))
        forward = controller.policy.q_values
        calls = []
        controller.policy.q_values = lambda *args: calls.append(1) or forward(*args)
        driver = policy_driver(controller, config, ModeWeights(config).mode('AGGP'))
        decision = driver.decide(env.graph, env.sim.snapshot, 0.0)
        assert len(calls) == 1 and set(decision.options) == set(env.graph.cav_ids()) == decision.began, \
            'the first decision begins every CAV an option'
        decision = driver.decide(env.graph, env.sim.snapshot, 0.5)
        assert len(calls) == 1 and not decision.began, 'every option is held: no forward pass'
        driver.set_mode(ModeWeights(config).mode('CONP'))   # a switch ends every option
        assert driver.decide(env.graph, env.sim.snapshot, 0.5).began and len(calls) == 2
    finally:
        env.close()


def test_the_options_table_says_whether_a_policy_drives_its_modes_as_they_are_named():
    from exit_decision.experiments.constant_options import table_markdown

    def row(run, seed, speed, headway):
        return {'run': run, 'seed': seed, 'variant': 'v', 'v_AVs': speed, 'headway_CAV': headway, 'return_AGGI': 1.0,
                'return_CONI': 1.0, **dict.fromkeys(('N_braking_CAV', 'N_braking', 'p_CAV', 'p_collision_CAV'), 1.0)}
    rows = [row(run, seed, speed + 0.1 * seed, headway) for seed in (1, 2, 3)
            for run, speed, headway in [('option_neutral', 15, 1.8), ('sumo', 15, 1.8), ('p@AGGI', 16, 1.5),
                                        ('p@CONI', 15, 2.0), ('q@AGGI', 15, 2.0), ('q@CONI', 16, 1.5)]]
    rows[-4]['headway_CAV'] = float('nan')   # p@AGGI on seed 3 had no leader in range: left out of the headway
    text = table_markdown(rows, ['AGGI', 'CONI'], 'v', 'option_neutral', orderings=[('AGGI', 'CONI')])
    assert ('- `p`: AGGI − CONI speed +1.000 m/s [+1.000, +1.000] (as named); '
            'CONI − AGGI time headway +0.500 s [+0.500, +0.500] (as named)') in text
    assert '- `q`: AGGI − CONI speed -1.000 m/s [-1.000, -1.000] (reversed)' in text


def test_the_readme_table_gives_one_row_when_the_neutral_driver_is_the_best_fixed_one():
    from exit_decision.experiments.constant_options import readme_table

    def row(run, seed, aggi):
        return {'run': run, 'seed': seed, 'variant': 'v', 'return_AGGI': aggi,
                **dict.fromkeys(('v_AVs', 'headway_CAV', 'N_braking_CAV', 'N_braking', 'p_CAV', 'p_collision_CAV'), 1.0)}
    rows = [row(run, seed, aggi + seed) for seed in (1, 2) for run, aggi in
            [('option_neutral', 10), ('option_close', 9), ('sumo', 9), ('p@AGGI', 9)]]
    lines = [line for line in readme_table(rows, ['AGGI'], 'v', 'p', 'option_neutral').splitlines() if line.startswith('| AGGI')]
    assert [line.split(' | ')[1] for line in lines] == [
        'the shipped policy', 'the best fixed driver (`neutral`, the neutral driver)', "SUMO's drivers"]
    assert lines[0].endswith('-1.000 [-1.000, -1.000] ↓ | -1.000 [-1.000, -1.000] ↓ |')
    assert lines[1].endswith('— | — |')

"""Config files load, and bad values are refused with the file and key named."""
import shutil

import pytest
import yaml

from exit_decision.config import ConfigError, default_config_dir, load_project


@pytest.fixture()
def config_copy(tmp_path):
    target = tmp_path / 'config'
    shutil.copytree(default_config_dir(), target)
    return target


def edit(path, change):
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data))


def test_shipped_config_loads_with_the_papers_values(project_config):
    scenario = project_config.scenario
    assert scenario.total_vehicles == 60
    assert scenario.vehicle_classes['HV2'].insertion_probability == 0.08
    assert scenario.road.highway_lengths == (150.0, 200.0, 150.0)
    assert set(project_config.modes) >= {'AGGI', 'AGGP', 'CONI', 'CONP', 'A1a', 'A1b', 'A1c', 'A1d'}
    assert project_config.mode('AGGP').decision_weights.efficiency == 0.35
    assert project_config.mode('CONP').punishment == 0.6


def test_out_of_range_value_names_file_and_key(config_copy):
    edit(config_copy / 'scenario.yaml',
         lambda d: d['vehicle_classes']['HV1'].__setitem__('insertion_probability', 1.5))
    with pytest.raises(ConfigError) as error:
        load_project(config_copy)
    assert 'scenario.yaml' in str(error.value)
    assert 'vehicle_classes.HV1.insertion_probability' in str(error.value)


def test_unknown_key_is_refused_not_ignored(config_copy):
    edit(config_copy / 'graph.yaml', lambda d: d.__setitem__('sensing_rnage', 40))
    with pytest.raises(ConfigError, match='sensing_rnage'):
        load_project(config_copy)


def test_depart_lane_off_the_road_is_refused(config_copy):
    edit(config_copy / 'scenario.yaml', lambda d: d['vehicle_classes']['HV3'].__setitem__('depart_lane', 3))
    with pytest.raises(ConfigError, match='vehicle_classes.HV3.depart_lane'):
        load_project(config_copy)


def test_unknown_mode_is_named_with_the_known_ones(project_config):
    with pytest.raises(ConfigError, match="unknown mode 'FAST'.*AGGI"):
        project_config.mode('FAST')


def test_env_naming_an_unknown_mode_fails_at_load(config_copy):
    edit(config_copy / 'env.yaml', lambda d: d.__setitem__('mode', 'FAST'))
    with pytest.raises(ConfigError, match='FAST'):
        load_project(config_copy)


def test_a_new_mode_needs_only_yaml(config_copy):
    edit(config_copy / 'modes.yaml', lambda d: d['modes'].__setitem__('MINE', {
        'decision_weights': {'result': 0.5, 'efficiency': 0.2, 'comfort': 0.1, 'safety': 0.2},
        'incentive': 0.5, 'punishment': 0.5}))
    assert load_project(config_copy).mode('MINE').incentive == 0.5


def test_a_mode_cannot_bring_its_own_demonstrator(config_copy):
    """One neutral teacher for every mode: what separates the modes is the reward alone."""
    edit(config_copy / 'modes.yaml', lambda d: d['modes']['AGGI'].__setitem__('rule_based', {'time_headway': 0.9}))
    with pytest.raises(ConfigError, match=r'modes\.AGGI\.rule_based(.|\n)*Extra inputs'):
        load_project(config_copy)


def test_conditioning_on_an_unknown_mode_is_named(config_copy):
    edit(config_copy / 'training.yaml', lambda d: d['conditioning'].__setitem__('modes', ['AGGI', 'FAST']))
    with pytest.raises(ConfigError, match="conditioning.modes: unknown mode 'FAST'"):
        load_project(config_copy)


def test_a_published_row_naming_an_unknown_reward_is_named(config_copy):
    edit(config_copy / 'training.yaml',
         lambda d: d['methods']['dueling_ddqn_per']['published'].__setitem__('reward_variant', 'paper_999'))
    with pytest.raises(ConfigError, match=r"methods\.dueling_ddqn_per\.published\.reward_variant: unknown 'paper_999'; known: .*paper_002"):
        load_project(config_copy)


def test_a_baseline_with_a_published_block_gets_its_published_row(project_config):
    training = project_config.training
    published = training.method('dqn_published')
    assert (published.measures, published.reward_variant, published.encoder) == (False, 'paper_002', 'grid')
    assert training.of_method('dqn_published').demonstrations.episodes == 0
    assert training.method('dqn').measures and 'gqn_published' not in training.method_names
    with pytest.raises(ConfigError, match="unknown method 'gqn_published'; known: .*dqn_published"):
        training.method('gqn_published')


def test_scenario_override_merges_over_the_base(tmp_path):
    override = tmp_path / 'dense.yaml'
    override.write_text('vehicle_classes:\n  HV1: {count: 33}\n')
    config = load_project(scenario_override=override)
    assert config.scenario.vehicle_classes['HV1'].count == 33
    assert config.scenario.vehicle_classes['HV1'].insertion_probability == 0.18


def test_broken_yaml_names_the_file(config_copy):
    (config_copy / 'modes.yaml').write_text('modes: [unclosed\n')
    with pytest.raises(ConfigError, match='modes.yaml: not valid YAML'):
        load_project(config_copy)


def test_yaml_that_would_run_code_is_refused(config_copy, tmp_path):
    """The (C) loader stays a safe one: a Python tag is an error, not a call."""
    marker = tmp_path / 'ran'
    (config_copy / 'modes.yaml').write_text(f'modes: !!python/object/apply:os.system ["touch {marker}"]\n')
    with pytest.raises(ConfigError, match='modes.yaml: not valid YAML'):
        load_project(config_copy)
    assert not marker.exists()

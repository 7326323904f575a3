"""The prior over options (issue 39): each fixed style's mean reward vector, from which the best
fixed style for any weights is a dot product away; it travels in a checkpoint and drives."""
import numpy as np
import pytest
import torch

from exit_decision.driving.prior import PriorTable
from exit_decision.model.modes import ModeWeights
from exit_decision.reward import VECTOR_COLUMNS, scalar, weights_of_input


def rows_of(style_vectors: dict, seeds=(1, 2), variant='headway'):
    """constant_options.csv rows: per style and seed its reward vector's columns (the mean is the given one)."""
    rows = []
    for style, vector in style_vectors.items():
        for k, seed in enumerate(seeds):
            spread = (-1) ** k * 0.5   # seeds differ, the mean stays
            rows.append({'run': f'option_{style}', 'seed': str(seed), 'variant': variant,
                         **{column: str(value + spread) for column, value in zip(VECTOR_COLUMNS, np.ravel(vector))}})
    return rows


#: a fast style that earns efficiency and pays safety, a calm one the other way round
FAST = np.array([[10.0, 0.0], [30.0, -1.0], [3.0, -2.0], [5.0, -8.0]])
CALM = np.array([[10.0, 0.0], [20.0, 0.0], [4.0, 0.0], [15.0, 0.0]])


def test_the_best_style_is_the_argmax_of_a_dot_product_for_any_weights(project_config):
    rows = rows_of({'fast': FAST, 'calm': CALM}) + rows_of({'fast': FAST}, variant='other')
    table = PriorTable.from_rows(rows, 'headway', ['fast', 'calm'])
    np.testing.assert_allclose(table.vectors['fast'], FAST)
    assert table.seeds == (1, 2) and table.variant == 'headway'
    modes = ModeWeights(project_config)
    for name in project_config.modes:
        weights = modes.mode(name).weights
        expected = max(('fast', 'calm'), key=lambda s: scalar({'fast': FAST, 'calm': CALM}[s], weights_of_input(weights)))
        assert table.best_style(weights) == expected
    efficiency_only = np.array([0.0, 1.0, 0.0, 0.0, 0.5, 0.5])
    safety_only = np.array([0.0, 0.0, 0.0, 1.0, 0.5, 0.5])
    assert table.best_style(efficiency_only) == 'fast' and table.best_style(safety_only) == 'calm', \
        'the prior follows the weights, not a mode name'


def test_a_table_with_a_style_missing_or_on_other_seeds_is_refused():
    with pytest.raises(ValueError, match='calm'):
        PriorTable.from_rows(rows_of({'fast': FAST}), 'headway', ['fast', 'calm'])
    with pytest.raises(ValueError, match='different seeds'):
        PriorTable.from_rows(rows_of({'fast': FAST}) + rows_of({'calm': CALM}, seeds=(1, 3)), 'headway', ['fast', 'calm'])


def test_the_table_travels_in_a_checkpoints_metadata_and_loads_with_weights_only(tmp_path):
    table = PriorTable('headway', (1, 2), {'fast': FAST, 'calm': CALM})
    torch.save({'metadata': {'prior': table.to_metadata()}}, tmp_path / 'p.pt')
    loaded = PriorTable.from_metadata(torch.load(tmp_path / 'p.pt', weights_only=True)['metadata']['prior'])
    assert loaded.variant == 'headway' and loaded.seeds == (1, 2) and list(loaded.vectors) == ['fast', 'calm']
    np.testing.assert_array_equal(loaded.vectors['calm'], CALM)


def test_the_prior_measured_in_the_environment_drives_the_best_style_of_its_mode(tmp_path):
    from exit_decision.agents.options import OptionSpace
    from exit_decision.config import load_project
    from exit_decision.driving.episode import play_episode
    from exit_decision.driving.prior import PriorDriver
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.evaluate import constant_option_episodes, prior_of
    from ros_helpers import small_config_dir

    config = load_project(small_config_dir(tmp_path / 'config'))
    env = ExitDecisionEnv(config)
    try:
        table = prior_of(env, constant_option_episodes(env, [7]))
        assert list(table.vectors) == list(config.env.options.styles) and table.variant == env.reward_variant
        modes = ModeWeights(config)
        driver = PriorDriver(table, OptionSpace(config, env.shield, env.planner), modes.mode('AGGI'))
        assert driver.style == table.best_style(modes.mode('AGGI').weights)
        held = set()
        play_episode(env, driver, 7, lambda decision, *_: held.update(o.option.style for o in decision.options.values()))
        assert held == {driver.style}, 'every CAV holds the best style for the mode'
        vector = env.episode_log.reward_vector
        np.testing.assert_allclose(vector, table.vectors[driver.style])   # one seed: the table is that episode
    finally:
        env.close()


def test_the_batched_best_style_is_the_scalar_one_at_every_weight_point(project_config):
    """Training's targets take the prior's option per transition from its weight multipliers."""
    table = PriorTable('headway', (1, 2), {'fast': FAST, 'calm': CALM})
    rng = np.random.default_rng(0)
    decision = rng.dirichlet(np.ones(4), size=50)
    incentive = rng.random(50)
    weights = np.column_stack([decision, incentive, 1.0 - incentive])
    chosen = table.best_indices(weights_of_input(weights))
    assert [list(table.vectors)[i] for i in chosen] == [table.best_style(w) for w in weights]
    assert set(chosen) == {0, 1}, 'both styles are best somewhere on the simplex'


def test_an_anchored_choice_departs_only_where_the_bound_beats_the_margin():
    from exit_decision.driving.anchored import Anchor

    prior = 0
    # two members, one row each of three CAV rows; options: 0 (the prior's), 1, 2
    q = np.array([[[1.0, 1.5, 0.9], [1.0, 3.0, 1.1], [1.0, 1.2, 1.0]],
                  [[2.0, 2.5, 1.9], [1.0, -0.5, 1.1], [1.0, 1.2, 1.0]]])
    greedy = Anchor(kappa=0.0, margin=0.0).scores(q, prior)
    assert greedy.argmax(1).tolist() == [1, 1, 1], 'kappa 0, margin 0: the greedy choice of the members\' mean'
    cautious = Anchor(kappa=1.0, margin=0.0).scores(q, prior)
    assert cautious.argmax(1).tolist() == [1, 2, 1], \
        'the members disagree on row 1\'s option 1: its bound falls below the agreed, smaller gain of option 2'
    assert Anchor(kappa=1.0, margin=0.3).scores(q, prior).argmax(1).tolist() == [1, 0, 0], \
        'gains under the margin fall back to the prior'
    one = Anchor(kappa=5.0, margin=0.0).scores(q[:1], prior)
    assert one.argmax(1).tolist() == [1, 1, 1], 'one member has no spread: only the margin gates it'


def test_the_prior_driver_explores_around_its_option(tmp_path):
    """Training with ``exploration.around: prior``: a CAV begins the prior's option unless it explores."""
    from exit_decision.agents.options import OptionSpace
    from exit_decision.config import load_project
    from exit_decision.driving.episode import play_episode
    from exit_decision.driving.prior import PriorDriver
    from exit_decision.env import ExitDecisionEnv
    from ros_helpers import small_config_dir

    config = load_project(small_config_dir(tmp_path / 'config'))
    env = ExitDecisionEnv(config)
    try:
        styles = list(config.env.options.styles)
        table = PriorTable('headway', (1,), {style: FAST if style == styles[0] else CALM for style in styles})
        space = OptionSpace(config, env.shield, env.planner)
        mode = ModeWeights(config).mode('AGGI')
        other = space.index('keep', styles[-1])
        calls = []

        def explore(mask):   # every third choice explores, where the option is allowed
            calls.append(other if len(calls) % 3 == 2 and mask[other] else None)
            return calls[-1]
        driver = PriorDriver(table, space, mode, explore=explore)
        prior = space.index('route', table.best_style(mode.weights))
        began = []
        play_episode(env, driver, 7, lambda decision, *_: began.extend(decision.actions[v] for v in decision.began))
        assert len(began) == len(calls) > 3 and other in began
        assert sorted(began) == sorted(prior if explored is None else explored for explored in calls), \
            'the options begun are the explored ones and, for the rest, the prior\'s'
    finally:
        env.close()


def test_one_step_gains_pair_each_option_with_the_prior_on_the_same_seed(tmp_path):
    """Is there anything to improve on the prior: the prior's own option, begun at the point, gains
    exactly 0 (the pairing holds); every other allowed option there is measured once."""
    from exit_decision.config import load_project
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.evaluate import constant_option_episodes, prior_of
    from exit_decision.evaluation.one_step import one_step_gains, summary
    from ros_helpers import small_config_dir

    config = load_project(small_config_dir(tmp_path / 'config'))
    env = ExitDecisionEnv(config)
    try:
        table = prior_of(env, constant_option_episodes(env, [7]))
        mode = ModeWeights(config).mode('AGGI')
        rows = one_step_gains(env, table, mode, env.reward_fn.weights(config.mode('AGGI')), [7], 1,
                              np.random.default_rng(0))
    finally:
        env.close()
    control = [row for row in rows if row['prior']]
    assert len(control) == 1 and control[0]['gain'] == 0.0
    assert control[0]['style'] == table.best_style(mode.weights) and control[0]['lane_intent'] == 'route'
    assert len(rows) > 2 and len({row['option'] for row in rows}) == len(rows), 'each allowed option once'
    assert any(row['gain'] != 0.0 for row in rows if not row['prior']), 'a deviation changes the episode'
    figures = summary(rows)
    assert figures['points'] == 1 and figures['control'] == 0.0 and figures['deviations'] == len(rows) - 1


def test_fresh_futures_measure_the_best_options_again_paired_with_the_prior(tmp_path):
    """The real gain of a point's best options: each again on fresh futures from the point, the
    prior on the same future; the futures differ (the prior's return moves), and a future is the
    same for the prior and the option (a second measurement repeats the first exactly)."""
    from exit_decision.config import load_project
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.evaluate import constant_option_episodes, prior_of
    from exit_decision.evaluation.one_step import fresh_future_gains, fresh_summary, one_step_gains
    from ros_helpers import small_config_dir

    config = load_project(small_config_dir(tmp_path / 'config'))
    env = ExitDecisionEnv(config)
    try:
        table = prior_of(env, constant_option_episodes(env, [7]))
        mode, weights = ModeWeights(config).mode('AGGI'), env.reward_fn.weights(config.mode('AGGI'))
        rows = one_step_gains(env, table, mode, weights, [7], 2, np.random.default_rng(1))
        fresh = fresh_future_gains(env, table, mode, weights, rows, 3, 2, 0.05)
        again = fresh_future_gains(env, table, mode, weights, rows, 3, 2, 0.05)
    finally:
        env.close()
    points = sorted({row['point'] for row in rows})
    assert [(row['point'], row['rank'], row['future']) for row in fresh] == [
        (point, rank, future) for point in points for future in range(3) for rank in range(2)]
    for point in points:
        best = max((row for row in rows if not row['prior'] and row['point'] == point), key=lambda row: row['gain'])
        assert all(row['option'] == best['option'] and row['first_gain'] == best['gain']
                   for row in fresh if row['rank'] == 0 and row['point'] == point)
    assert [row['gain'] for row in fresh] == [row['gain'] for row in again], 'a future is reproducible'
    assert len({row['prior_return'] for row in fresh}) > 1, 'the futures differ'
    figures = fresh_summary(fresh)
    assert figures['points'] == 2 and figures['prior_spread'] > 0
    assert figures['fresh_low'] <= figures['fresh_mean'] <= figures['fresh_high']
    per_point = [np.mean([row['gain'] for row in fresh if row['rank'] == 0 and row['point'] == point]) for point in points]
    assert figures['fresh_median'] == pytest.approx(np.median(per_point))
    assert figures['fresh_mean'] == pytest.approx(np.mean([row['gain'] for row in fresh if row['rank'] == 0]))

"""The figures drawn from CSVs alone (exit-decision plot, compare --report-only, tradeoff
--plot-only): what they put on their axes, from small hand-made inputs."""
from pathlib import Path

import pytest

from exit_decision.evaluation import plots
from exit_decision.experiments import comparison_report, tradeoff
from exit_decision.tables import write_rows

SEEDS = range(10000, 10006)


@pytest.fixture
def captured(monkeypatch):
    """The figures ``save`` is given, kept open for inspection (and still written)."""
    figures = []

    def keep(fig, path, layout=True):
        if layout:
            fig.tight_layout()
        fig.savefig(path, dpi=40)
        figures.append(fig)
        return path
    monkeypatch.setattr(plots, 'save', keep)
    monkeypatch.setattr(comparison_report, 'save', keep)
    return figures


def episodes(reward: float, v_avs: float = 16.0, step: float = 0.1) -> list[dict]:
    return [{'seed': seed, 'reward': reward + step * i, 'v_AVs': v_avs + 0.1 * i, 'v_s': 18.0, 'p_CAV': 1.0}
            for i, seed in enumerate(SEEDS)]


def test_a_run_name_splits_into_driver_and_mode_only_at_a_mode_shared_by_runs():
    modes, drivers = plots.runs_by_mode(['policy_AGGI', 'rule_based_headway_0.8_AGGI', 'policy_CONP',
                                         'rule_based_headway_0.8_CONP'])
    assert modes == ['AGGI', 'CONP'] and drivers == ['policy', 'rule_based_headway_0.8']
    assert plots.runs_by_mode(['rule_based', 'sumo']) == ([''], ['rule_based', 'sumo'])


def test_test_reward_draws_paired_differences_from_the_teacher_on_an_axis_around_them(tmp_path, captured):
    evaluation = tmp_path / 'evaluation'
    for mode, base in (('AGGI', 19.0), ('CONP', 13.0)):
        write_rows(evaluation / f'rule_based_{mode}.csv', episodes(base))
        write_rows(evaluation / f'policy_{mode}.csv', episodes(base + 0.3, step=0.11))
        write_rows(evaluation / f'sumo_{mode}.csv', episodes(base - 0.2))
    assert plots.test_reward(evaluation, tmp_path).is_file()
    axes = captured[0].axes
    assert [ax.get_title() for ax in axes] == ['AGGI (rule_based: 19.25)', 'CONP (rule_based: 13.25)']
    assert [t.get_text() for t in axes[0].get_yticklabels()] == ['policy', 'sumo']
    low, high = axes[0].get_xlim()
    assert -0.5 < low < -0.2 and 0.3 < high < 0.7, 'the axis spans the differences (+0.3, -0.2), not the returns'
    means = [line.get_xdata()[0] for line in axes[0].lines if line.get_marker() == 'o']
    assert means == pytest.approx([0.325, -0.2])


def test_speeds_are_drawn_per_mode_on_an_axis_around_them(tmp_path, captured):
    evaluation = tmp_path / 'evaluation'
    for mode in ('AGGI', 'CONP'):
        for driver in ('rule_based', 'policy'):
            write_rows(evaluation / f'{driver}_{mode}.csv', episodes(13.0))
    assert plots.speeds(evaluation, tmp_path).is_file()
    axes = captured[0].axes
    assert [ax.get_title() for ax in axes] == ['AGGI', 'CONP']
    assert axes[0].get_xlim()[0] > 10, 'speeds of 16-18 m/s: the axis does not start at 0'


def validation_run(directory: Path, returns: list[float], decisions: list[int]) -> None:
    """A run's logs: one training row per episode, a validation at episodes 0, 2, 4 ..."""
    write_rows(directory / 'training.csv', [{'episode': e, 'decisions': d, 'reward': -50.0, 'steps': 700}
                                            for e, d in enumerate(decisions)])
    write_rows(directory / 'validation.csv', [{'episode': 2 * k, 'mode': 'CONP', 'return': r, 'teacher_return': 13.4}
                                              for k, r in enumerate(returns)])


def test_the_learning_curves_show_the_greedy_validation_return_against_decisions(tmp_path, captured):
    training = tmp_path / 'training'
    validation_run(training / 'a_s0', [12.0, 12.5, 13.0], [100, 200, 300, 400])
    validation_run(training / 'a_s1', [11.0, 12.5, 12.0], [150, 250, 350, 450])
    write_rows(training / 'b_s0' / 'training.csv', [{'episode': e, 'decisions': 100 * (e + 1), 'reward': 2.0 + e}
                                                    for e in range(30)])   # no validation log
    x, returns, teacher = comparison_report.validation_points(training / 'a_s0', 'CONP')
    assert list(x) == [0, 200, 400] and list(returns) == [12.0, 12.5, 13.0] and teacher == 13.4
    out = comparison_report.learning_curves(training, {'a': ['a_s0', 'a_s1'], 'b': ['b_s0']}, tmp_path / 'c.png',
                                            'CONP')
    assert out.is_file()
    ax = captured[0].axes[0]
    handles, labels = ax.get_legend_handles_labels()
    assert sorted(labels) == ['a (2 seeds)', 'b (1 seeds; exploring training return, no validation log)',
                              'teacher (validation seeds)']
    curve = handles[labels.index('a (2 seeds)')].lines[0]   # the errorbar's line through the means
    assert list(curve.get_ydata()) == pytest.approx([11.5, 12.5, 12.5]), 'the mean over seeds, candidate by candidate'
    assert 13.4 in [line.get_ydata()[0] for line in ax.lines if line.get_linestyle() == ':']


def test_the_variant_figure_draws_each_method_against_the_teacher_around_the_differences(tmp_path, captured):
    per_variant = {variant: {'rule_based': {'CONP': episodes(base)}, 'sumo': {'CONP': episodes(base + 0.4)},
                             'dqn': {'CONP': episodes(base - 0.3)}}
                   for variant, base in (('base', 13.0), ('dense', 19.0))}
    assert comparison_report.variant_figure(per_variant, 'CONP', tmp_path / 'v.png').is_file()
    ax = captured[0].axes[0]
    assert sorted(ax.get_legend_handles_labels()[1]) == ['dqn', 'rule_based (the teacher)', 'sumo']
    low, high = ax.get_ylim()
    assert -0.6 < low < -0.3 and 0.4 < high < 0.7, 'the axis on the differences (-0.3, +0.4), not on 13-19'
    assert [t.get_text() for t in ax.get_xticklabels()] == ['base\n(rule_based 13.25)', 'dense\n(rule_based 19.25)']


def test_the_tradeoff_is_redrawn_from_its_csv_with_names_that_do_not_overlap(tmp_path, project_config,
                                                                            monkeypatch):
    rows = [{'point': name, 'v_AVs': v, 'N_braking': b, 'safety_row': s, 'p_CAV': 1.0}
            for name, v, b, s in (('AGGI', 16.18, 6.45, 57.53), ('A1b', 16.165, 6.35, 57.65),
                                  ('sweep_0.50', 16.171, 6.35, 57.43), ('sweep_0.75', 16.200, 6.30, 57.37),
                                  ('sweep_1.00', 16.199, 6.30, 57.37))]
    write_rows(tmp_path / 'tradeoff.csv', rows)
    names, titles = [], []
    original = tradeoff.place_names

    def spy(ax, points, fontsize=7):
        original(ax, points, fontsize)
        renderer = ax.figure.canvas.get_renderer()
        names.append({text.get_text(): text.get_window_extent(renderer) for text in ax.texts})
        titles.append(ax.figure.texts[0].get_text())
    monkeypatch.setattr(tradeoff, 'place_names', spy)
    path = tradeoff.redraw_tradeoff(project_config, Path('policies/x/policy.pt'), 20, tmp_path)
    assert path == tmp_path / 'tradeoff.png' and path.stat().st_size > 0
    assert len(names) == 2, 'both panels'
    for boxes in names:
        assert sorted(boxes) == ['0.50', '0.75', '1.00', 'A1b', 'AGGI']
        extents = list(boxes.values())
        assert not any(a.overlaps(b) for i, a in enumerate(extents) for b in extents[i + 1:]), 'names overlap'
    assert titles[0].startswith('x: one checkpoint at every weight point (20 seeds each')


def test_fresh_futures_draw_each_points_best_option_first_look_against_its_fresh_mean(tmp_path, captured):
    """Issue 39's noise check: x = a point's best option's first gain, y = its mean on fresh
    futures with the interval; only the best (rank 0) is drawn, one panel per mode."""
    rows = [{'mode': mode, 'seed': 1, 'point': point, 'rank': rank, 'future': future, 'first_gain': first,
             'gain': fresh + 0.01 * future - (0.5 if rank else 0.0), 'prior_return': 6.0 + 0.1 * future}
            for mode in ('AGGI', 'CONP') for point, first, fresh in ((3, 0.2, 0.0), (9, 0.1, 0.05))
            for rank in (0, 1) for future in range(3)]
    write_rows(tmp_path / 'fresh_futures.csv', rows)
    assert plots.fresh_futures(tmp_path, tmp_path).name == 'one_step_fresh_futures.png'
    axes = captured[0].axes
    assert [ax.get_title().split('\n')[0] for ax in axes] == ['AGGI: 2 points', 'CONP: 2 points']
    assert axes[0].get_yscale() == 'symlog', 'gains of 0.01 and of 20 on one axis'
    x, y = axes[0].lines[0].get_data()
    assert list(x) == [0.2, 0.1] and list(y) == pytest.approx([0.01, 0.06])
    assert 'fresh mean +0.035' in axes[0].get_title() and 'median +0.035' in axes[0].get_title()


def test_a_learning_curve_has_flattened_only_with_enough_validations_and_a_slope_reaching_zero():
    """Issue 39's budget: >= 6 validations in the last third, the fitted slope's 95% interval reaching 0."""
    import numpy as np

    from exit_decision.evaluation.statistics import last_third_slopes, slope_interval

    x = np.arange(10.0)
    slope, low, high = slope_interval(x, 2.0 * x + 1.0 + np.tile([0.1, -0.1], 5))
    assert low < slope < high and abs(slope - 2.0) < 0.05 and high - low < 0.2
    rising = [{'episode': e, 'mode': 'AGGI', 'gain': 0.01 * e} for e in range(0, 301, 20)]
    level = [{'episode': e, 'mode': 'CONP', 'gain': 0.3 + 0.02 * (-1) ** (e // 20)} for e in range(0, 301, 20)]
    sparse = [{'episode': e, 'mode': 'AGGP', 'gain': 0.3 + 0.02 * (-1) ** (e // 50)} for e in range(0, 301, 50)]
    fits = last_third_slopes(rising + level + sparse)
    assert fits['AGGI']['validations'] == fits['CONP']['validations'] == 6 and fits['AGGI']['from_episode'] == 200
    assert not fits['AGGI']['flat'] and fits['AGGI']['low'] > 0, 'still rising'
    assert fits['CONP']['flat'] and fits['CONP']['low'] <= 0 <= fits['CONP']['high']
    assert not fits['AGGP']['flat'], 'level, but 3 validations in its last third are too few'


def test_a_few_samples_get_students_t_interval():
    """Repeated futures of a point are few (3-10): their interval uses t, wider than the normal's."""
    import numpy as np

    from exit_decision.evaluation.statistics import paired_interval, t_interval

    mean, low, high = t_interval([1.0, 2.0, 3.0])
    assert mean == 2.0 and high - mean == mean - low == pytest.approx(4.303 / np.sqrt(3))
    assert high - low > paired_interval([1.0, 2.0, 3.0])[2] - paired_interval([1.0, 2.0, 3.0])[1]
    assert np.isnan(t_interval([1.0])[1])

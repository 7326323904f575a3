"""The results page's target and ordering checks on hand-made numbers."""
from exit_decision.evaluation.report import speed_orderings, step_cap_lines, target_checks
from exit_decision.tables import write_rows


def row(run, mode, reward, d_reward, low, high, p_cav=1.0, collisions=0.0, capped=0):
    return {'run': run, 'mode': mode, 'reward': reward, 'd_reward': d_reward, 'd_reward_low': low,
            'd_reward_high': high, 'p_CAV': p_cav, 'p_collision_CAV': collisions, 'capped': capped}


def test_targets_are_checked_against_the_teacher_on_the_numbers():
    comparison = [row('mdgqn_conditioned', 'AGGI', 19.0, 0.2, 0.1, 0.3),
                  row('mdgqn_conditioned', 'CONP', 13.0, 0.05, -0.02, 0.12, p_cav=0.985),
                  row('rule_based_headway_0.8', 'AGGI', 19.3, 0.5, 0.4, 0.6),
                  row('mdgqn_AGGI', 'AGGI', 19.2, 0.4, 0.3, 0.5)]
    text = '\n'.join(target_checks(comparison))
    assert '- AGGI: Exit-1 1.000 (>= 0.99), CAV collisions 0.0000 (<= 0.0067), 0 capped: met; ' \
           'return − teacher +0.200 [+0.100, +0.300]: beats the teacher' in text
    assert '- CONP: Exit-1 0.985 (>= 0.99)' in text and 'NOT met' in text and 'does NOT beat the teacher' in text
    assert 'best sanity-sweep driver under AGGI on these seeds (rule_based_headway_0.8): return 19.000 vs 19.300' in text
    assert 'per-mode network mdgqn_AGGI: return 19.000 vs 19.200 (-0.200, -1.0% of its magnitude' in text


def test_speed_orderings_are_paired_over_seeds(tmp_path):
    write_rows(tmp_path / 'run_AGGI.csv', [{'seed': s, 'v_AVs': 16.0 + 0.01 * s} for s in range(10)])
    write_rows(tmp_path / 'run_CONI.csv', [{'seed': s, 'v_AVs': 15.5 + 0.01 * s + 0.02 * (s % 2)} for s in range(10)])
    (line,) = speed_orderings(tmp_path, 'run', pairs=(('AGGI', 'CONI'),))
    assert line.startswith('- run: AGGI faster than CONI: v_AVs +0.490 m/s') and line.endswith('holds')


def test_episodes_cut_by_the_step_cap_are_counted_per_run(tmp_path):
    write_rows(tmp_path / 'mdgqn_conditioned_AGGI.csv', [{'steps': 1500.0}, {'steps': 800.0}, {'steps': 1500.0}])
    write_rows(tmp_path / 'rule_based_AGGI.csv', [{'steps': 820.0}])
    write_rows(tmp_path / 'mdgqn_conditioned_AGGI_actions.csv', [{'steps': 1500.0}])
    write_rows(tmp_path / 'comparison.csv', [{'steps': 1500.0}])
    assert step_cap_lines(tmp_path, 1500) == ['- mdgqn_conditioned_AGGI: 2 of 3 episodes ran into the 1500-step cap']
    assert step_cap_lines(tmp_path, 2000) == ['- none: no episode ran into the 2000-step cap']


def test_the_speed_section_links_the_benchmarks_logs_instead_of_copying_them(tmp_path):
    from exit_decision.evaluation.report import benchmark_lines
    logs = tmp_path / 'results' / 'benchmarks.txt'
    logs.parent.mkdir()
    (tmp_path / 'performance.md').write_text('# Performance\n')
    relative = lambda path: path.relative_to(tmp_path).as_posix()  # noqa: E731
    assert benchmark_lines(logs, relative) == [], 'no logs, no section'
    logs.write_text('$ exit-decision bench sim\nlibsumo 8209 steps/s\n')
    text = '\n'.join(benchmark_lines(logs, relative))
    assert '[`results/benchmarks.txt`](results/benchmarks.txt)' in text and '(performance.md)' in text
    assert '8209' not in text and '```' not in text


def test_the_readmes_verdict_and_table_are_what_report_writes_from_the_options_table():
    """The README's verdict (at its top) and results table are generated from the shipped options
    table of the test seeds, for the default algorithm; outside them the README says nothing is safe."""
    import re
    from pathlib import Path

    from exit_decision.config import load_project
    from exit_decision.evaluation.report import README_BLOCKS, variant_links
    from exit_decision.experiments.constant_options import neutral_run, readme_table, readme_verdict
    from exit_decision.model.names import DEFAULT_ALGORITHM
    from exit_decision.tables import read_rows

    repo = Path(__file__).resolve().parent.parent
    readme = (repo / 'README.md').read_text(encoding='utf-8')
    config = load_project()
    rows = read_rows(repo / 'docs/results/options/test_seeds/constant_options.csv')
    table = (rows, config.mode_matrix.modes, config.env.reward_variant, DEFAULT_ALGORITHM, neutral_run(config))

    def block(name: str) -> str:
        begin, end = README_BLOCKS[name]
        return readme.split(begin + '\n', 1)[1].split('\n' + end, 1)[0]
    assert block('verdict') == readme_verdict(*table)
    assert block('table').startswith(readme_table(*table, links=variant_links(repo / 'docs/results.md', 'docs/results.md')))
    assert readme.index(README_BLOCKS['verdict'][0]) < readme.index('\n## '), 'the verdict comes before the first section'
    outside = readme.replace(block('verdict'), '')
    assert not re.search(r'\bsafe(?:ly|r)?\b(?!-)', outside.split('## Glossary')[0], re.IGNORECASE)


def test_each_training_run_is_named_with_its_recipe_from_its_config(tmp_path):
    """The results page says how each policy was made (issue 39: the grid's MDGQN stays, by its recipe)."""
    import json

    from exit_decision.evaluation.report import training_lines

    def run(name, demonstrations, updates, episodes, seed, variant):
        (tmp_path / name).mkdir()
        (tmp_path / name / 'config.json').write_text(json.dumps({'episodes': episodes, 'seed': seed, 'config': {
            'training': {'demonstrations': {'episodes': demonstrations, 'pretrain_updates': updates}},
            'env': {'reward_variant': variant}}}))
        write_rows(tmp_path / name / 'validation.csv', [{'episode': 0, 'score': 0.1, 'mode': 'AGGI', 'gain': 0.1, 'p_CAV': 1.0}])
        return tmp_path / name

    grid, options = training_lines([run('mdgqn_conditioned', 160, 40000, 500, 0, 'calibrated'),
                                    run('gqn_options_conditioned', 0, 0, 600, 2, 'headway')])
    assert grid.startswith("- mdgqn_conditioned (the grid's MDGQN): 160 demonstration episodes, 40000 pre-training "
                           'updates, 500 RL episodes, seed 0, reward variant `calibrated`; kept the checkpoint of episode 0')
    assert options.startswith('- gqn_options_conditioned: no demonstrations, no pre-training, 600 RL episodes, seed 2, '
                              'reward variant `headway`;')

"""What the main job (``exit-decision stack``) prints at its end, for a reader who has not read
the code: the episodes' metrics in the README's words and units, where the mode switch landed
and why there, what it changed (one verdict line, beside the same seed without it), whether
the bag and the environment agree (one line), and what to do next."""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: (the README's name, metric, unit, format, what it is): the stack's episode events' metrics;
#: the all-vehicle figures are said in words beside the CAVs' (``ALSO``); braking_steps and
#: p_HV2 are left out
METRIC_LINES = (
    ('Exit-1 rate', 'p_CAV', '', '.2f', 'share of the CAVs that left by their target exit'),
    ('CAV collisions', 'p_collision_CAV', '', '.2f', 'share of the CAVs in a collision'),
    ('Speed', 'v_AVs', 'm/s', '.2f', "the CAVs' mean speed"),
    ('Hard brakings', 'N_braking', '', '.1f', 'runs of steps braking at {threshold:g} m/s² or harder, all vehicles'),
)
#: metric -> (words, the metric said in them, unit): beside a line of METRIC_LINES
ALSO = {'v_AVs': ('every vehicle\'s', 'v_s', 'm/s'), 'p_collision_CAV': ('all collisions per CAV', 'p_collision', '')}


def figure(values: Sequence[float], spec: str, unit: str) -> str:
    """A metric over episodes: the value of one episode; the mean ± std of several (NaNs left out)."""
    finite = [value for value in values if math.isfinite(value)]
    if not finite:
        return 'not measured'
    unit = f' {unit}' if unit else ''
    if len(finite) == 1:
        return f'{finite[0]:{spec}}{unit}'
    return f'{np.mean(finite):{spec}} ± {np.std(finite):{spec}}{unit}'


def metrics_lines(episodes: Sequence[dict[str, float]], braking_threshold: float, label: str = '') -> list[str]:
    """The metrics of the episodes the stack ran (``label``: who drove them), one per line, in
    the README's words."""
    steps = [episode['steps'] for episode in episodes]
    head = (f'{len(episodes)} episode, {steps[0]:.0f} steps' if len(episodes) == 1 else
            f'{len(episodes)} episodes (mean ± std over them), {min(steps):.0f}-{max(steps):.0f} steps')
    lines = [f'metrics{" of " + label if label else ""} ({head}):']
    for name, metric, unit, spec, what in METRIC_LINES:
        spec = '.0f' if len(episodes) == 1 and spec == '.1f' else spec   # a count of one episode is whole
        text = f'  {name:<15} {figure([e.get(metric, math.nan) for e in episodes], spec, unit):<16} ' \
               f'{what.format(threshold=abs(braking_threshold))}'
        if metric in ALSO:
            words, other, other_unit = ALSO[metric]
            text += f' ({words}: {figure([e.get(other, math.nan) for e in episodes], spec, other_unit)})'
        lines.append(text)
    return lines


@dataclass(frozen=True)
class SwitchTiming:
    """The steps of one switch: asked for (--switch-at), requested (the state the launcher had
    seen when it called the service), landed (the first decision in the new mode)."""
    asked: int
    requested: int
    landed: int
    interval: int            # simulation steps per decision
    step_length: float       # [s]


def timing_line(before: str, after: str, timing: SwitchTiming) -> str:
    """Where the switch landed, and why there: the launcher acts on the first state it sees at
    or past the step asked for, the service answers, and the node's next decision is the first
    in the new mode."""
    interval_s = timing.interval * timing.step_length
    return (f'switch {before} -> {after}: asked for at step {timing.asked}, requested at step {timing.requested}, '
            f'in force from step {timing.landed} ({timing.landed * timing.step_length:.1f} s). Why later: the launcher '
            f'calls the decision node\'s set_parameters service (as ros2 param set does) at the first state it sees '
            f'at or past step {timing.asked}, the bridge runs on meanwhile, and the node decides every '
            f'{timing.interval} steps ({interval_s:g} s): its first decision after the answer is the first in {after}.')


def compare(value: float, other: float, spec: str, unit: str) -> str:
    """``value`` beside ``other`` (the run without the switch), and their difference if any."""
    unit = f' {unit}' if unit else ''
    text = f'{value:{spec}} against {other:{spec}}{unit}'
    if math.isnan(value) or math.isnan(other) or f'{value:{spec}}' == f'{other:{spec}}':
        return text
    return f'{text} ({value - other:+{spec}})'


def changed(value: float, other: float, tolerance: float, words: tuple[str, str, str]) -> str:
    """More, less or the same (``words``), within ``tolerance``."""
    if math.isnan(value) or math.isnan(other) or abs(value - other) <= tolerance:
        return words[2]
    return words[0] if value > other else words[1]


def verdict_line(outcome) -> str:
    """One line: what the switch changed for the CAVs on the road at it over the window after
    it, against the same seed without it (``outcome``: a ``ros.bags.switch.SwitchOutcome``)."""
    (_, switched), (_, kept), switch = outcome.switched, outcome.kept, outcome.switch
    speed = changed(switched.speed, kept.speed, 0.05, ('faster', 'slower', 'as fast'))
    headway = changed(switched.headway, kept.headway, 0.02,
                      ('longer time headways', 'shorter time headways', 'the same time headways'))
    brakings = changed(switched.hard_brakings, kept.hard_brakings, 0,
                       ('more hard brakings', 'fewer hard brakings', 'as many hard brakings'))
    return (f'verdict: switching to {switch.after} made the {switched.cavs} CAVs on the road at it drive {speed}, '
            f'with {headway} and {brakings}, over the {outcome.window:g} s after it than the same seed in '
            f'{switch.before} throughout: speed {compare(switched.speed, kept.speed, ".2f", "m/s")}, time headway '
            f'{compare(switched.headway, kept.headway, ".2f", "s")}, hard brakings '
            f'{compare(switched.hard_brakings, kept.hard_brakings, "d", "")}.')


def agree(one, other) -> bool:
    """Two runs' (before, after) figures agree, to the digits printed."""
    return all(a.cavs == b.cavs and a.hard_brakings == b.hard_brakings and
               all(round(x, 2) == round(y, 2) or math.isnan(x) and math.isnan(y)
                   for x, y in ((a.speed, b.speed), (a.headway, b.headway)))
               for a, b in zip(one, other))


def consistency_line(outcome) -> str:
    """One line: whether the environment's re-run with the same switch drove as the stack did
    (the bag), which makes the comparison without the switch like for like."""
    if agree(outcome.bag, outcome.switched):
        return (f'consistency check: the environment (no ROS) re-ran seed {outcome.seed} with the same switch and '
                f'drove as the stack did in the bag (the same speed, time headway and hard brakings around the '
                f'switch), so the comparison above is like for like.')
    (_, bag), (_, env) = outcome.bag, outcome.switched
    return (f'consistency check FAILED: the environment\'s re-run of seed {outcome.seed} with the same switch '
            f'drove otherwise than the stack in the bag (after the switch, environment against bag: speed '
            f'{compare(env.speed, bag.speed, ".2f", "m/s")}, time headway {compare(env.headway, bag.headway, ".2f", "s")}, '
            f'hard brakings {compare(env.hard_brakings, bag.hard_brakings, "d", "")}): the comparison above is not '
            f'like for like (was the bag recorded with another policy or config?).')


def returns_line(outcome) -> str:
    """The return of the episode with the switch under each mode's weights for the part it drove."""
    switch, (before, after) = outcome.switch, outcome.returns
    return (f'return (the sum of the rewards; from the environment\'s re-run): under {switch.before}\'s weights for '
            f'steps 0-{switch.step - 1}, which {switch.before} drove, {before:.2f}; under {switch.after}\'s '
            f'weights for steps {switch.step}-{outcome.last_step}, which {switch.after} drove, {after:.2f}.')


def next_lines(bag: Path, log_dir: Path) -> list[str]:
    """What to do with the run's files."""
    return ['next:',
            f'  exit-decision show {bag}     a time-space diagram and a bird\'s-eye clip of each episode',
            f'  ros2 bag info {bag}          the bag\'s topics and message counts (on a system ROS 2 install)',
            f'  exit-decision replay {bag}   decides the bag again and counts the matching commands',
            f'  the nodes\' logs: {log_dir}/']

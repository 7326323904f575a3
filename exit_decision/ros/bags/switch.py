"""A mode switch as a bag recorded it: the first decision in the new mode, and the states of
that episode around it (for ``evaluation.switch.switch_windows``)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from exit_decision.config import ProjectConfig
from exit_decision.ros.bags.storage import read_messages
from exit_decision.ros.messages.conversions import states_from_msg
from exit_decision.ros.topics import COMMANDS_TOPIC, STATES_TOPIC

if TYPE_CHECKING:
    from exit_decision.evaluation.switch import Steps


@dataclass(frozen=True)
class RecordedSwitch:
    episode: int
    step: int              # the first decision in the new mode
    time: float            # [s] simulation time of that step
    before: str            # the mode of the decisions before it
    after: str
    steps: Steps           # the episode's (time, vehicles), every recorded step


def recorded_switch(bag: Path, config: ProjectConfig) -> RecordedSwitch | None:
    """The first mode switch in ``bag`` (None if its decisions keep one mode); BagError if it
    cannot be read."""
    dt, sections = config.scenario.step_length, config.scenario.road.names.sections
    switch, previous, episode, steps = None, None, None, []   # steps: the states of the episode read now
    for topic, _, _, msg in read_messages(bag, {COMMANDS_TOPIC, STATES_TOPIC}):
        if topic == STATES_TOPIC:
            if msg.episode != episode:
                if switch is not None:
                    break                      # the switch's episode is over
                episode, steps = msg.episode, []
            steps.append((msg.step * dt, states_from_msg(msg, sections)))
        elif switch is None:
            if previous is not None and msg.episode == previous.episode and msg.mode != previous.mode:
                switch = (msg.episode, msg.step, previous.mode, msg.mode)
            previous = msg
    if switch is None:
        return None
    switched_in, step, before, after = switch
    return RecordedSwitch(switched_in, step, step * dt, before, after, steps if episode == switched_in else [])


def switch_report(bag: Path, config: ProjectConfig, policy_dir: Path, algorithm: str, seed: int,
                  window: float = 10.0) -> str:
    """What the first switch in ``bag`` did to the CAVs on the road at it (``window`` s before and
    after): as the stack drove it, and the same seed in the environment with the same switch and
    without it (the mode before throughout), like for like; a line saying so without a switch."""
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.switch import policy_steps, switch_table, switch_windows
    from exit_decision.driving.policy import policy_driver
    from exit_decision.model.modes import ModeWeights
    from exit_decision.model.names import planned, policy_path
    from exit_decision.model.policy import ACTION_SPACES, load_controller

    switch = recorded_switch(bag, config)
    if switch is None:
        return f'{bag}: its decisions keep one mode: no switch to show'
    threshold = config.scenario.emergency_braking_threshold
    modes = ModeWeights(config)
    env = ExitDecisionEnv(config, mode=switch.before)
    figures = [(f'the stack (bag), {switch.before} -> {switch.after}',
                switch_windows(switch.steps, switch.time, window, threshold))]
    try:
        which = planned(algorithm, switch.before)
        controller = load_controller(config, policy_path(policy_dir, *which), env.shield, env.planner, which,
                                     ACTION_SPACES)
        driver, episode_seed = policy_driver(controller, config), seed + switch.episode
        for label, after in ((f'environment, {switch.before} -> {switch.after}', switch.after),
                             (f'environment, {switch.before} throughout', None)):
            driver.set_mode(modes.mode(switch.before))
            steps = policy_steps(env, driver, episode_seed, switch.time + window,
                                 None if after is None else (switch.time, modes.mode(after)))
            figures.append((label, switch_windows(steps, switch.time, window, threshold)))
    finally:
        env.close()
    return (f'the switch {switch.before} -> {switch.after} at t = {switch.time:.1f} s (step {switch.step}) of seed '
            f'{episode_seed}, {figures[0][1][0].cavs} CAVs on the road:\n' + switch_table(figures, window))

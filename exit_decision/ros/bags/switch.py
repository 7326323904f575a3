"""A mode switch as a bag recorded it: the first decision in the new mode, and the states of
that episode around it (for ``evaluation.switch.switch_windows``); and what it did, beside the
same seed in the environment with and without it (``switch_outcome``)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from exit_decision.config import ProjectConfig
from exit_decision.ros.bags.storage import read_messages
from exit_decision.ros.messages.conversions import states_from_msg
from exit_decision.ros.topics import COMMANDS_TOPIC, STATES_TOPIC

if TYPE_CHECKING:
    from exit_decision.evaluation.switch import Steps, WindowFigures


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


@dataclass(frozen=True)
class SwitchOutcome:
    """A recorded switch beside the same seed in the environment, with the same switch and
    without it (the mode before throughout): each run's (before, after) figures of the CAVs on
    the road at it, and the returns of the run with the switch under each mode's weights for
    the part of the episode that mode drove."""
    switch: RecordedSwitch
    seed: int
    window: float                                     # [s] each side of the switch
    bag: tuple[WindowFigures, WindowFigures]
    switched: tuple[WindowFigures, WindowFigures]     # environment, the same switch
    kept: tuple[WindowFigures, WindowFigures]         # environment, the mode before throughout
    returns: tuple[float, float]                      # under before's weights until the switch, after's from it
    last_step: int                                    # the episode's last step (environment, the same switch)


def switch_outcome(bag: Path, config: ProjectConfig, policy_dir: Path, algorithm: str, seed: int,
                   window: float = 10.0) -> SwitchOutcome | None:
    """What the first switch in ``bag`` did (None: its decisions keep one mode): as the stack
    drove it, and the same seed in the environment with the same switch and without it, like
    for like, each to the episode's end."""
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.switch import policy_steps, switch_windows
    from exit_decision.driving.policy import policy_driver
    from exit_decision.model.modes import ModeWeights
    from exit_decision.model.names import planned, policy_path
    from exit_decision.model.policy import ACTION_SPACES, load_controller
    from exit_decision.reward import scalar

    switch = recorded_switch(bag, config)
    if switch is None:
        return None
    threshold = config.scenario.emergency_braking_threshold
    modes = ModeWeights(config)
    env = ExitDecisionEnv(config, mode=switch.before)
    try:
        which = planned(algorithm, switch.before)
        controller = load_controller(config, policy_path(policy_dir, *which), env.shield, env.planner, which,
                                     ACTION_SPACES)
        driver, episode_seed = policy_driver(controller, config), seed + switch.episode
        runs = []
        for after in (switch.after, None):
            driver.set_mode(modes.mode(switch.before))
            runs.append(policy_steps(env, driver, episode_seed,
                                     switch=None if after is None else (switch.time, modes.mode(after))))
        weights = {name: env.reward_fn.weights(config.mode(name)) for name in (switch.before, switch.after)}
    finally:
        env.close()
    switched, kept = runs
    return SwitchOutcome(switch, episode_seed, window, switch_windows(switch.steps, switch.time, window, threshold),
                         switch_windows(switched.steps, switch.time, window, threshold),
                         switch_windows(kept.steps, switch.time, window, threshold),
                         (float(scalar(switched.before, weights[switch.before])),
                          float(scalar(switched.after, weights[switch.after]))),
                         round(switched.steps[-1][0] / config.scenario.step_length))

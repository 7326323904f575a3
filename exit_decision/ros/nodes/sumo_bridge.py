"""sumo_bridge: owns the embedded SUMO scenario and puts it on ROS 2 topics.

Publishes /clock (simulation time), the vehicle states of every step and episode events
(start; end with the metrics); applies the CAV commands it receives. Timing:
- synchronous (default): on a decision step (every ``decision_interval`` steps) it waits
  for the commands answering that step, up to ``command_timeout`` (then warns, holds the
  previous commands and goes on): deterministic, the mode for evaluation;
- realtime: steps on a wall-clock schedule (``realtime_factor`` x real time) and applies
  the newest commands that arrived.
In synchronous mode /diagnostics also has the bridge's wait for the commands of a decision
step, from just before it publishes that step's states to the commands accepted
(``decision_wait_ms_median``, ``_p99``, ``_max`` over the last DECISION_WAIT_WINDOW decision
steps): the state-to-command latency as the simulation sees it.
Commands are taken at every step (in synchronous mode too, where only a decision step's are
awaited: a flood's are dropped as they come, not all in the next decision's wait) and checked
on arrival. A message is rejected whole, counted on /diagnostics and
changes nothing (in synchronous mode the bridge goes on waiting for a good answer) when it
cannot answer now: another episode, or (synchronous) any step but the one waited on,
(realtime) a step not after the last accepted one or after the current one. So is a message
with a non-finite acceleration, a lane change outside the grid or a vehicle twice, and bytes
that are no little-endian CDR CavCommandArray with single NUL-terminated UTF-8 strings (the
bridge decodes the bytes itself, ``commands_cdr``). Finite accelerations outside the action
grid are clamped to it and counted. A command for a vehicle
that is not a controlled CAV on the road is rejected alone; the step goes on.
"""
from __future__ import annotations

import time
from collections import deque

import numpy as np
import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from exit_decision_msgs.msg import CavCommandArray, EpisodeEvent, VehicleStateArray
from rclpy.executors import SingleThreadedExecutor
from rosgraph_msgs.msg import Clock

from exit_decision.config.seeds import TEST_SEED
from exit_decision.env import ExitDecisionEnv
from exit_decision.ros.diagnostics import Diagnostics
from exit_decision.ros.executor import Waiter, run_node, take_waiting
from exit_decision.ros.intake import Intake
from exit_decision.ros.parameters import (check_choice, declare, declare_config, declare_cpu_affinity,
                                          declare_thread_priority, describe, follow)
from exit_decision.ros.topics import (CLOCK_QOS, CLOCK_TOPIC, COMMANDS_QOS, COMMANDS_TOPIC, EPISODE_TOPIC, EVENT_QOS,
                                      STATES_QOS, STATES_TOPIC)
from exit_decision.ros.messages.commands_cdr import decode_commands
from exit_decision.ros.messages.conversions import episode_event_to_msg, stamp_of
from exit_decision.ros.messages.states_cdr import encode_states
from exit_decision.scenario.simulation import CommandError
from exit_decision.traffic import CavCommand
from exit_decision.input_checks import CommandLimits, InputError

PEER_REPORT_PERIOD = 5.0   # [s] how often a bridge waiting for its peers says what it waits for
DECISION_WAIT_WINDOW = 1000   # decision steps the wait figures on /diagnostics cover


class SumoBridge(Node):
    def __init__(self):
        super().__init__('sumo_bridge')
        self.config = declare_config(self)
        declare_thread_priority(self)
        declare_cpu_affinity(self)
        def p(name, default, descriptor):
            return declare(self, name, default, descriptor)
        self.timing = p('timing', 'synchronous', describe(
            'synchronous: wait for the commands of each decision step; realtime: step on a wall timer',
            read_only=True, constraints='synchronous | realtime'))
        check_choice('timing', self.timing, ('synchronous', 'realtime'))
        # applied live (follow below): the timeout from the next wait, the factor from the next
        # step, the episode count at the next episode's start; the rest is used at start only
        self.command_timeout = p('command_timeout', 1.0, describe(
            '[s] synchronous mode: longest wait for the commands of a decision step; applies from the next wait',
            float_range=(0.001, 60.0)))
        self.realtime_factor = p('realtime_factor', 1.0, describe(
            'realtime mode: simulated seconds per wall-clock second; applies from the next step',
            float_range=(0.01, 1000.0)))
        self.episodes = p('episodes', 1, describe('episodes to run, 0 = until stopped; a new value applies '
                                                  'before the next episode starts', integer_range=(0, 1_000_000)))
        self.seed = p('seed', TEST_SEED, describe('seed of the first episode (then +1 each)', read_only=True,
                                               integer_range=(0, 2**31 - 1)))
        self.startup_timeout = p('startup_timeout', 0.0, describe(
            '[s] at start, wait at most this long for the peers (wait_for_subscribers; in synchronous policy '
            'mode a commands publisher too), then start anyway; 0: wait until they come', read_only=True,
            float_range=(0.0, 3600.0)))
        self.wait_for_subscribers = p('wait_for_subscribers', 1, describe(
            'at start, wait for this many subscribers of the states, e.g. a recorder that must not miss the '
            'first step', read_only=True, integer_range=(0, 100)))
        follow(self, 'command_timeout', 'realtime_factor', 'episodes')
        cav_driver = p('cav_driver', 'policy', describe(
            'policy: CAVs follow the commands; sumo: SUMO drives them (reference runs)', read_only=True,
            constraints='policy | sumo'))
        check_choice('cav_driver', cav_driver, ('policy', 'sumo'))
        self.limits = CommandLimits.of(self.config.env.actions)
        self.env = ExitDecisionEnv(self.config, cav_driver=cav_driver)
        self.wait_for_decision_node = self.timing == 'synchronous' and cav_driver == 'policy'
        self.interval = self.config.env.decision_interval
        self.step_length = self.config.scenario.step_length
        self.clock_pub = self.create_publisher(Clock, CLOCK_TOPIC, CLOCK_QOS)
        self.states_pub = self.create_publisher(VehicleStateArray, STATES_TOPIC, STATES_QOS)
        self.events_pub = self.create_publisher(EpisodeEvent, EPISODE_TOPIC, EVENT_QOS)
        self.diagnostics = Diagnostics(self, 'sumo_bridge')
        # its one subscription: its wait for commands takes this queue only, and nothing else the
        # process could be sent (other topics) reaches it
        self.commands = Intake.of_config(self, self.diagnostics, self.config).subscribe(
            CavCommandArray, COMMANDS_TOPIC, self.on_commands, COMMANDS_QOS, raw=True,
            window=self.command_window, refuse=self.refuse_commands)
        self.episode = 0
        self.published_step = -1            # step of the newest published states
        self.awaiting: int | None = None    # synchronous: the step whose commands are waited for
        self.last_command_step = -1         # realtime: step of the newest accepted commands
        self.pending: dict[str, CavCommand] | None = None   # accepted, not yet applied
        self.published_at = 0.0                              # monotonic time just before the newest states went out
        self.decision_waits: deque[float] = deque(maxlen=DECISION_WAIT_WINDOW)   # [s] synchronous: states -> commands
        self.diagnostics.figures.append(self.decision_wait_figures)
        self.executor_ = SingleThreadedExecutor(context=self.context)
        self.executor_.add_node(self)
        self.waiter = Waiter([self], self.executor_)   # the waits of the loop: commands taken without an executor pass
        self.get_logger().info(f'{self.timing} bridge, {self.episodes or "unlimited"} episode(s) from seed '
                               f'{self.seed}, decisions every {self.interval} steps')

    # --- commands -----------------------------------------------------------------------------

    def command_window(self) -> tuple[int, int, int]:
        """(episode, first step, last step) of the commands that can answer now: synchronous, the
        step waited for (none when not waiting); realtime, a step after the last accepted up to
        the newest published."""
        if self.timing == 'synchronous':
            return (self.episode, self.awaiting, self.awaiting) if self.awaiting is not None else (self.episode, 1, 0)
        return self.episode, self.last_command_step + 1, self.published_step

    def refuse_commands(self, episode: int, step: int, amount: int = 1) -> None:
        """Reject and count (``rejected_stale_commands``, out of sequence) ``amount`` command messages
        outside ``command_window``, said with the reason of the one of (``episode``, ``step``)."""
        _, first, last = self.command_window()
        if episode != self.episode:
            reason = f'episode {episode} is not the current episode {self.episode}'
        elif self.timing == 'realtime':
            reason = f'step {step} is not in {first}..{last}'
        else:
            reason = f'step {step}: waiting for step {first}' if first <= last else f'step {step}: not waiting for commands'
        self.diagnostics.reject('stale_commands', 'commands', reason, COMMANDS_TOPIC, 'out_of_sequence', amount)

    def on_commands(self, raw: bytes) -> None:
        """Accept (checked, clamped) the commands that can answer now; reject the rest whole:
        first one that cannot answer now (``command_window``, read from its header alone: the
        intake drops most of those before they reach Python), then a message with a bad field.
        Decoded from the CDR bytes (``commands_cdr``): the bridge waits on it."""
        peeked = self.diagnostics.step_of(raw, 'command_messages', COMMANDS_TOPIC)
        if peeked is None:
            return
        episode, first, last = self.command_window()
        if peeked[0] != episode or not first <= peeked[1] <= last:
            self.refuse_commands(*peeked)
            return
        what, cause = 'commands', 'undecodable'
        try:
            msg = decode_commands(raw)
            what, cause = f'commands of step {msg.step}', 'invalid'
            commands, clamped = self.limits.sanitize(msg.commands)
        except InputError as error:
            self.diagnostics.reject('command_messages', what, str(error), COMMANDS_TOPIC, cause)
            return
        if clamped:
            self.diagnostics.count('clamped_commands', clamped)
            self.get_logger().warning(f'commands of step {msg.step}: {clamped} acceleration(s) clamped to '
                                      f'[{self.limits.acceleration_min:g}, {self.limits.acceleration_max:g}]',
                                      throttle_duration_sec=5.0)
        self.pending, self.last_command_step = commands, msg.step
        self.awaiting = None

    def take_commands(self) -> dict | None:
        """The accepted commands not applied yet, each one that cannot be applied now (its
        vehicle is not a controlled CAV on the road) rejected and counted."""
        commands, self.pending = self.pending, None
        if commands is None:
            return None
        accepted = {}
        for vehicle_id, command in commands.items():
            try:
                self.env.sim.validate_commands({vehicle_id: command})
                accepted[vehicle_id] = command
            except CommandError as error:
                self.diagnostics.reject('commands', 'a command', str(error))
        self.diagnostics.count('applied_commands', len(accepted))
        return accepted

    def wait_for_commands(self, step: int) -> dict | None:
        self.pending, self.awaiting = None, step
        deadline = time.monotonic() + self.command_timeout
        try:
            take_waiting(self.commands)   # the whole queue at once: a flood on the topic cannot bury the answer
            while self.pending is None:   # each pass of the wait takes the queue when something comes
                if not rclpy.ok(context=self.context):
                    return None
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self.diagnostics.count('command_timeouts')
                    self.get_logger().warning(f'no commands for step {step} within {self.command_timeout} s: '
                                              'holding the previous ones', throttle_duration_sec=5.0)
                    return None
                self.waiter.spin_once(remaining)
            self.decision_waits.append(time.monotonic() - self.published_at)
            return self.take_commands()
        finally:
            self.awaiting = None

    # --- publishing -----------------------------------------------------------------------------

    def decision_wait_figures(self) -> dict[str, float]:
        if not self.decision_waits:
            return {}
        waits = np.array(self.decision_waits) * 1000
        return {'decision_wait_ms_median': float(np.median(waits)),
                'decision_wait_ms_p99': float(np.percentile(waits, 99)),
                'decision_wait_ms_max': float(waits.max()), 'decision_wait_steps': len(waits)}

    def publish_state(self, result) -> None:
        self.clock_pub.publish(Clock(clock=stamp_of(result.time)))
        encoded = encode_states(result.vehicles, episode=self.episode, step=result.step, step_length=self.step_length)
        self.published_at = time.monotonic()
        self.states_pub.publish(encoded)
        self.published_step = result.step

    def publish_event(self, event: int, seed: int, result) -> None:
        m = self.env.episode_log.metrics() if event == EpisodeEvent.EVENT_ENDED else None
        msg = episode_event_to_msg(event, episode=self.episode, seed=seed, steps=result.step, time=result.time,
                                   metrics=m, truncated=bool(m and result.truncated and not result.terminated))
        if m:
            self.get_logger().info(f'episode {self.episode} (seed {seed}) ended after {result.step} steps: '
                                   f'p_CAV {m["p_CAV"]:.3f}, p_collision_CAV {m["p_collision_CAV"]:.3f}, '
                                   f'v_AVs {m["v_AVs"]:.2f} m/s')
        self.events_pub.publish(msg)

    # --- the loop ---------------------------------------------------------------------------------

    def run_episode(self, seed: int) -> None:
        self.env.reset(seed=seed)
        result = self.env.sim.state
        self.pending, self.published_step, self.last_command_step = None, -1, -1
        # The nodes follow the episode from its first states after this event. No wait for its
        # acknowledgements: Fast DDS acknowledges with its periodic heartbeat, so a 1 s wait for
        # them always ran out (1 s lost at every episode's start). It reaches a node before the
        # states published after it (in order from this participant), and a node that meets states
        # of an episode it does not know takes its waiting events first (graph_builder,
        # decision_node); a node that still misses the first step costs that step's command timeout,
        # as the wait did.
        self.publish_event(EpisodeEvent.EVENT_STARTED, seed, result)
        next_tick = time.monotonic()
        while rclpy.ok(context=self.context):
            self.publish_state(result)
            if result.terminated or result.truncated:
                break
            if self.timing == 'synchronous':
                # the executor spins (parameter services, late messages) while it waits on a decision
                # step; a spin on every step would cost each step ~0.35 ms of the 2 cores for nothing
                if result.step % self.interval == 0:
                    commands = self.wait_for_commands(result.step)
                else:   # commands are taken as they come, so a flood's are not all left to the next decision's wait
                    take_waiting(self.commands)
                    commands = None
            else:
                next_tick += self.step_length / self.realtime_factor
                if next_tick <= time.monotonic():
                    self.waiter.keep_serving()   # behind its schedule it never waits: parameters still answered
                while (wait := next_tick - time.monotonic()) > 0:
                    self.waiter.spin_once(wait)
                take_waiting(self.commands)
                commands = self.take_commands()
            result, _ = self.env.simulate_step(commands)
        self.publish_event(EpisodeEvent.EVENT_ENDED, seed, result)

    def missing_peers(self) -> str:
        """What the bridge still waits for before its first step, in words ('' when nothing).
        Peers are counted as matched by the middleware, not as seen on the ROS graph: a reliable
        message to a matched reader arrives (resent until acknowledged), so the first step needs
        no time to settle after the count."""
        missing = []
        listening = self.states_pub.get_subscription_count()
        if listening < self.wait_for_subscribers:
            missing.append(f'{self.wait_for_subscribers - listening} more subscriber(s) of {STATES_TOPIC} '
                           f'({listening} of wait_for_subscribers {self.wait_for_subscribers})')
        if self.wait_for_decision_node and not self.commands.get_publisher_count():
            missing.append(f'a publisher of {COMMANDS_TOPIC} (the decision node)')
        return ' and '.join(missing)

    def wait_for_peers_to_listen(self) -> None:
        """Do not step before the subscribers are there (and, in synchronous policy mode,
        someone who can answer): as long as it takes (a node started alone, as by `ros2 run`,
        waits for the others), or ``startup_timeout`` seconds if that is set; saying every
        PEER_REPORT_PERIOD seconds what is missing."""
        started = report = time.monotonic()
        while rclpy.ok(context=self.context):
            missing = self.missing_peers()
            if not missing:
                return
            now = time.monotonic()
            if self.startup_timeout and now - started >= self.startup_timeout:
                self.get_logger().warning(f'still waiting for {missing} after startup_timeout '
                                          f'{self.startup_timeout:g} s: starting anyway')
                return
            if now >= report:
                self.get_logger().info(f'waiting for {missing}')
                report = now + PEER_REPORT_PERIOD
            self.executor_.spin_once(timeout_sec=0.1)

    def run(self) -> None:
        self.wait_for_peers_to_listen()
        while rclpy.ok(context=self.context) and (self.episodes == 0 or self.episode < self.episodes):
            self.run_episode(self.seed + self.episode)
            self.episode += 1
        self.diagnostics.publish()
        # Exiting right away could drop the last (reliable) messages: wait until the
        # subscribers (the launcher, a recorder) have acknowledged them.
        for publisher in (self.states_pub, self.events_pub):
            publisher.wait_for_all_acked(Duration(seconds=5.0))
        self.get_logger().info('all episodes done')

    def destroy_node(self) -> None:
        self.env.close()
        super().destroy_node()


def main() -> int:
    return run_node('sumo_bridge', SumoBridge, lambda node: node.run())


if __name__ == '__main__':
    raise SystemExit(main())

"""exit_decision: graph RL highway-exit decisions for CAVs (SUMO + ROS 2).

Importing the package registers ``exit_decision/HighwayExit-v0`` with gymnasium (by entry
point string: the simulation, rclpy and torch load only when an env is made) and offers
``exit_decision.parallel_env``, the PettingZoo form (``exit_decision.ecosystem``, loaded on
first use).
"""
import gymnasium

ENV_ID = 'exit_decision/HighwayExit-v0'

if ENV_ID not in gymnasium.registry:
    gymnasium.register(ENV_ID, entry_point='exit_decision.ecosystem:make_env')


def __getattr__(name: str):
    """``parallel_env`` from ``exit_decision.ecosystem``, imported on first use (PEP 562)."""
    if name == 'parallel_env':
        from exit_decision.ecosystem import parallel_env
        return parallel_env
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')

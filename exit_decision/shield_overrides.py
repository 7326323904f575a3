"""Which CAVs the safety shield overrode in a decision: per CAV, the command its driver
preferred (before any mask) and the command it was given (``Decision.refused``).
Used by the decision node (published on /exit_decision/shield_overrides) and ``evaluate --show``.
"""
from __future__ import annotations

from dataclasses import dataclass

from exit_decision.actions import ActionGrid
from exit_decision.agents.shield import Decision
from exit_decision.traffic import CavCommand


@dataclass(frozen=True, slots=True)
class ShieldOverride:
    preferred: CavCommand        # what the CAV's driver wanted
    applied: CavCommand          # what the shield let it do (the command sent)


def shield_overrides(decision: Decision, grid: ActionGrid) -> dict[str, ShieldOverride]:
    """The CAVs of ``decision`` whose preferred action the shield refused, by vehicle id."""
    return {vehicle_id: ShieldOverride(grid.command(preferred), grid.command(decision.actions[vehicle_id]))
            for vehicle_id, preferred in decision.refused.items()}

"""The schema of every file under ``config/`` (pydantic): unknown keys are refused, so a typo
cannot silently fall back to a default, and each field says what it allows."""
from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]
Probability = Annotated[float, Field(ge=0, le=1)]
Count = Annotated[int, Field(ge=0)]          # may be 0
PositiveInt = Annotated[int, Field(gt=0)]
NegativeFloat = Annotated[float, Field(lt=0)]
UnitInterval = Annotated[float, Field(gt=0, le=1)]   # (0, 1]


class ConfigError(ValueError):
    """A configuration file is missing, unreadable or invalid; the message says where."""


class Strict(BaseModel):
    model_config = ConfigDict(extra='forbid', frozen=True)


SchemaT = TypeVar('SchemaT', bound=BaseModel)


def _format_error(path: Path, error: ValidationError) -> str:
    lines = [f'{path}: invalid configuration']
    for item in error.errors():
        key = '.'.join(str(part) for part in item['loc'] if not str(part).startswith('function-'))
        lines.append(f'  {key or "(top level)"}: {item["msg"]} (got {item.get("input")!r})')
    return '\n'.join(lines)


def parse(schema: type[SchemaT], data: object, source: Path | str = '<dict>') -> SchemaT:
    """Validate already-loaded data against a schema; raise ConfigError naming the keys."""
    try:
        return schema.model_validate(data)
    except ValidationError as error:
        raise ConfigError(_format_error(Path(source), error)) from None


def deep_merge(base: dict, override: dict) -> dict:
    """Return base with override applied key by key (nested dicts merged, others replaced)."""
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


# --- scenario ---------------------------------------------------------------------------

#: An edge id of the generated network: SUMO's lane ids append ``_<index>``, ':' starts its internal ids.
EdgeName = Annotated[str, Field(pattern=r'^[A-Za-z][A-Za-z0-9_.-]*$')]


class RoadNames(Strict):
    """The edge ids of the road: code asks for an edge by its role, never by its name."""
    sections: tuple[EdgeName, EdgeName, EdgeName]   # highway sections, upstream to downstream
    first_exit: EdgeName     # ramp off lane 0 at the end of the first section (HV3 leaves by it)
    target_exit: EdgeName    # ramp off lane 0 at the end of the second section: every CAV's task

    @model_validator(mode='after')
    def _distinct(self) -> RoadNames:
        names = [*self.sections, self.first_exit, self.target_exit]
        repeated = sorted({name for name in names if names.count(name) > 1})
        if repeated:
            raise ValueError(f'each edge needs its own name; repeated: {", ".join(repeated)}')
        return self


class RoadConfig(Strict):
    names: RoadNames
    lane_count: Annotated[int, Field(ge=1, le=6)]
    highway_lengths: Annotated[tuple[PositiveFloat, PositiveFloat, PositiveFloat],
                               Field(description='[m] of each of names.sections')]
    ramp_length: PositiveFloat
    highway_speed_limit: PositiveFloat
    ramp_speed_limit: PositiveFloat
    diverge_commit_distance: PositiveFloat


class CollisionConfig(Strict):
    action: Literal['remove', 'warn', 'teleport', 'none']
    mingap_factor: NonNegativeFloat
    check_junctions: bool


class VehicleClassConfig(Strict):
    count: Count
    insertion_probability: Probability
    depart_speed: NonNegativeFloat
    depart_lane: Literal['random'] | Count
    right_change_clearance: NonNegativeFloat | None = None


class VehicleTypeConfig(Strict):
    length: PositiveFloat
    max_speed: PositiveFloat
    accel: PositiveFloat
    decel: PositiveFloat
    emergency_decel: PositiveFloat
    speed_factor: PositiveFloat
    speed_dev: NonNegativeFloat
    politeness: Probability
    car_following: Literal['IDM', 'Krauss', 'EIDM']


#: the vehicle classes of the scenario (paper 000 Table 1), the one place they are named
HV1, HV2, HV3, CAV = 'HV1', 'HV2', 'HV3', 'CAV'
VEHICLE_CLASSES = (HV1, HV2, HV3, CAV)


class ScenarioConfig(Strict):
    step_length: PositiveFloat
    max_steps: PositiveInt
    sumo_seed_offset: Count
    road: RoadConfig
    collision: CollisionConfig
    vehicle_classes: dict[Literal[VEHICLE_CLASSES], VehicleClassConfig]
    vehicle_types: dict[Literal[VEHICLE_CLASSES], VehicleTypeConfig]
    emergency_braking_threshold: NegativeFloat

    @model_validator(mode='after')
    def _every_class_defined(self) -> ScenarioConfig:
        for section in ('vehicle_classes', 'vehicle_types'):
            missing = [c for c in VEHICLE_CLASSES if c not in getattr(self, section)]
            if missing:
                raise ValueError(f'{section}: missing classes {missing}')
        for name, cls in self.vehicle_classes.items():
            if isinstance(cls.depart_lane, int) and cls.depart_lane >= self.road.lane_count:
                raise ValueError(f'vehicle_classes.{name}.depart_lane: {cls.depart_lane} is not a '
                                 f'lane of a {self.road.lane_count}-lane road')
        if self.vehicle_classes[HV2].right_change_clearance is None:
            raise ValueError('vehicle_classes.HV2.right_change_clearance: required')
        return self

    @property
    def total_vehicles(self) -> int:
        return sum(c.count for c in self.vehicle_classes.values())


# --- graph ------------------------------------------------------------------------------

class GraphConfig(Strict):
    max_vehicles: PositiveInt
    sensing_range: PositiveFloat
    feature_set: Literal['paper', 'relative']


# --- reward and modes -------------------------------------------------------------------

class SubRewardValues(Strict):
    """One number per reward row (result, efficiency, comfort, safety)."""
    result: float
    efficiency: float
    comfort: float
    safety: float


class ModeConfig(Strict):
    decision_weights: SubRewardValues
    incentive: Probability
    punishment: Probability


class ModeRow(Strict):
    incentive: str
    punished: str


class ModeMatrix(Strict):
    """The paper's 2 x 2 matrix of modes (Table 3): a style per row, a result weighting per column."""
    aggressive: ModeRow
    conservative: ModeRow

    @property
    def modes(self) -> list[str]:
        """Row by row: aggressive incentive, aggressive punished, conservative incentive, conservative punished."""
        return [self.aggressive.incentive, self.aggressive.punished,
                self.conservative.incentive, self.conservative.punished]

    @property
    def aggressive_orderings(self) -> list[tuple[str, str]]:
        """(aggressive, conservative) mode pairs of each column: the first faster, with shorter gaps."""
        return [(self.aggressive.incentive, self.conservative.incentive),
                (self.aggressive.punished, self.conservative.punished)]

    @property
    def speed_orderings(self) -> list[tuple[str, str]]:
        """(faster, slower) pairs the modes' names promise: aggressive over conservative in each
        column, incentive over punished in each row."""
        return self.aggressive_orderings + [(row.incentive, row.punished) for row in (self.aggressive, self.conservative)]


class ModesConfig(Strict):
    modes: dict[str, ModeConfig]
    matrix: ModeMatrix


class SpeedBounds(Strict):
    highway: NonNegativeFloat
    ramp: NonNegativeFloat


class CausedBrakingConfig(Strict):
    """The ``traffic`` variant's MOBIL-style term (reward.py ``MatrixReward.caused_braking``):
    a vehicle decelerating harder than ``b_safe`` charges ``weight`` per m/s^2 of the excess,
    per simulation step, to the comfort punishment of its leader if that is a CAV."""
    b_safe: PositiveFloat                # [m/s^2] MOBIL's safe deceleration; beyond it, the leader pays
    weight: PositiveFloat                # raw comfort punishment per m/s^2 of excess, per step
    leader_range: PositiveFloat          # [m] bumper gap within which the leader is held responsible


class MatrixRewardConfig(Strict):
    kind: Literal['matrix']
    exponent_cap: PositiveFloat | None
    lane_change_cap: PositiveInt | None
    dynamic_weights: bool
    comfort_vehicles: Literal['all', 'cav']
    incentive_per: Literal['step', 'metre']
    # the safe-gaps incentive: Table 4's regions as read (per step of safe time gaps), or per
    # metre driven graded by the time headway kept (reward.py MatrixReward.headway_grade)
    safety_incentive: Literal['hazard_diagram', 'headway'] = 'hazard_diagram'
    headway_full: PositiveFloat = 3.0   # [s] the headway that earns the whole safe-gaps incentive
    # the hard braking a CAV causes to its follower, on the CAV's comfort punishment (None: not priced)
    caused_braking: CausedBrakingConfig | None = None
    v_min: SpeedBounds
    scales: SubRewardValues

    @model_validator(mode='after')
    def _positive_scales(self) -> MatrixRewardConfig:
        for key, value in self.scales.model_dump().items():
            if value <= 0:
                raise ValueError(f'scales.{key}: must be > 0, got {value}')
        return self


class BaselineRewardConfig(Strict):
    kind: Literal['baseline']
    intention: float
    speed: float
    lane_change: float
    collision: float


class TermsRewardConfig(Strict):
    """Papers 002 and 003 (exit_decision/reward.py ``TermsReward``): a weighted sum of each
    CAV's terms; per-step terms are counted per simulation step times ``step_weight``."""
    kind: Literal['terms']
    collision: float                 # per collision the CAV is in
    speed: float                     # per step, times (v - v_min) / (lane limit - v_min) in [0, 1]
    v_min: SpeedBounds
    lane_change: float               # per lane change of the CAV
    step: float                      # per step on the road
    clean_exit: float                # once, for a CAV that leaves the road (never collided)
    step_weight: PositiveFloat


class IntentionRewardConfig(Strict):
    """Paper 001's eq. 2-5 (exit_decision/reward.py ``IntentionReward``)."""
    kind: Literal['intention']
    intention_weight: float          # w_I
    collision_weight: float          # w_C
    on_route: float                  # R_I per step in a lane of the route to the target exit
    off_route: float                 # R_I per step in another lane
    reached: float                   # R_I once, leaving by the target exit
    missed: float                    # R_I once, leaving by another exit
    speed_max: PositiveFloat         # [m/s] v_max of R_S = v / v_max - speed_offset
    speed_offset: float
    step_weight: PositiveFloat


RewardVariantConfig = MatrixRewardConfig | BaselineRewardConfig | TermsRewardConfig | IntentionRewardConfig
RewardVariant = Annotated[RewardVariantConfig, Field(discriminator='kind')]


class RewardConfig(Strict):
    variants: dict[str, RewardVariant]


# --- environment ------------------------------------------------------------------------

class ActionGridConfig(Strict):
    lane_changes: tuple[Literal[-1, 0, 1], ...]
    acceleration_min: float
    acceleration_max: float
    acceleration_step: PositiveFloat

    @model_validator(mode='after')
    def _ordered(self) -> ActionGridConfig:
        if self.acceleration_max < self.acceleration_min:
            raise ValueError('acceleration_max: must be >= acceleration_min')
        if len(set(self.lane_changes)) != len(self.lane_changes) or 0 not in self.lane_changes:
            raise ValueError('lane_changes: must be distinct and include 0 (keep)')
        return self


class ShieldConfig(Strict):
    lane_gap: bool
    gap_front: NonNegativeFloat
    gap_back: NonNegativeFloat
    gap_back_time: NonNegativeFloat
    gap_reservation: bool
    stop_capable: bool
    ego_max_braking: PositiveFloat
    leader_max_braking: PositiveFloat
    stop_margin: NonNegativeFloat
    human_follower_braking: bool
    hard_braking: NegativeFloat
    human_follower_distance: NonNegativeFloat


class RuleBasedConfig(Strict):
    """The rule-based driver (demonstrator and baseline); see agents/rule_based.py."""
    max_acceleration: PositiveFloat
    comfortable_braking: PositiveFloat
    time_headway: NonNegativeFloat
    standstill_gap: NonNegativeFloat
    gap_search_speed: NonNegativeFloat
    firm_braking: PositiveFloat
    urgent_braking: PositiveFloat
    urgency_distance: PositiveFloat
    # the options' low level (env.yaml options.low_level) turns these on; the grid's teacher
    # and lane planner keep them off (their policies were trained that way)
    overspeed_time: PositiveFloat | None = None    # [s] None: IDM's free term above the desired speed
    # CAVs know each other: no lane change that forces a CAV follower into hard braking, and a
    # CAV makes room for one merging ahead of it within make_room_distance
    connected_cavs: bool = False
    make_room_distance: NonNegativeFloat = 15.0    # [m]


#: a learned policy's action space: the 81-action grid (paper 000) or options (issue 28)
ActionSpaceName = Literal['grid', 'options']


class OptionsConfig(Strict):
    """The options action space (issue 28; exit_decision/agents/options.py)."""
    hold_time: PositiveFloat                     # [s] an option ends after this long at the latest
    lane_intents: list[Literal['keep', 'left', 'right', 'route']]
    low_level: dict[str, float | bool]           # rule_based keys over env.yaml's, for every style
    styles: dict[str, dict[str, float]]          # name -> rule_based keys over env.yaml's and low_level
    planner_style: str | None = None             # the style of a CAV the lane planner drives (None: its option's)
    route_only_before: NonNegativeFloat = 0.0    # [m] before the first exit's junction end: route intents only

    @property
    def neutral_style(self) -> str:
        """The neutral driver's style: the planner's (``planner_style``), else the first style.
        The demonstrations and the tables' reference drive it."""
        return self.planner_style or next(iter(self.styles))

    @model_validator(mode='after')
    def _styles(self) -> OptionsConfig:
        if not self.styles:
            raise ValueError('styles: at least one style is needed')
        if self.planner_style not in (None, *self.styles):
            raise ValueError(f'planner_style: {self.planner_style!r} is not a style; styles: {", ".join(self.styles)}')
        if 'keep' not in self.lane_intents or len(set(self.lane_intents)) != len(self.lane_intents):
            raise ValueError(f'lane_intents: each at most once, keep among them, got {self.lane_intents}')
        known = set(RuleBasedConfig.model_fields)
        for name, keys in [('low_level', self.low_level), *((f'styles.{n}', k) for n, k in self.styles.items())]:
            unknown = sorted(set(keys) - known)
            if unknown:
                raise ValueError(f'{name}: unknown rule_based key {unknown[0]!r} '
                                 f'(allowed: {", ".join(sorted(known))})')
        return self

    def style(self, base: RuleBasedConfig, name: str) -> RuleBasedConfig:
        """The driver parameters of a style: ``base`` (env.yaml rule_based), the low level's
        keys, then the style's."""
        return RuleBasedConfig.model_validate({**base.model_dump(), **self.low_level, **self.styles[name]})


class EnvConfig(Strict):
    decision_interval: PositiveInt
    actions: ActionGridConfig
    shield: ShieldConfig
    rule_based: RuleBasedConfig
    options: OptionsConfig
    lane_planner: bool
    reward_variant: str
    mode: str


# --- training -------------------------------------------------------------------------------

EncoderName = Literal['graph', 'graph_paper', 'grid', 'nearest']   # exit_decision/encoders.py


class NetworkConfig(Strict):
    encoder: list[PositiveInt]       # per-row layers
    gcn: Count                       # 0: no graph convolution
    head: list[PositiveInt]
    dueling: bool = False
    adjacency_input: bool = False    # (no GCN) each row's adjacency row is part of its input


class PrioritizedReplayConfig(Strict):
    alpha: Probability
    beta: Probability


class PublishedConfig(Strict):
    """What a baseline's "as published" row changes: its paper's reward and exploration."""
    reward_variant: str              # a key of config/reward.yaml, used in training
    training: dict = {}              # over the method's own settings (its paper's exploration)


PUBLISHED_SUFFIX = '_published'


class MethodConfig(Strict):
    """A learned method: a state encoder, a network and a loss (issue 11)."""
    paper: str
    description: str
    encoder: EncoderName
    network: NetworkConfig
    double: bool                     # the bootstrap action chosen by the online network
    multi_step: PositiveInt          # m of the m-step target
    prioritized: PrioritizedReplayConfig | None = None
    single_agent: bool = False       # SGRL: one CAV learns, the others drive as humans in training
    training: dict = {}              # the method's own settings over this file's (e.g. paper 003's)
    published: PublishedConfig | None = None   # adds the method <name>_published
    # false (as on every <name>_published): without our measures, i.e. only lanes that exist
    # masked, no lane planner, no demonstrations
    measures: bool = True
    reward_variant: str | None = None   # the reward it learns from; None: config/env.yaml's

    def as_published(self) -> MethodConfig:
        """The method as its paper published it (``published`` must be set)."""
        p = self.published
        return self.model_copy(update={
            'description': f'{self.description}; as published (its reward, its exploration, no shield, '
                           'no lane planner, no demonstrations)',
            'training': deep_merge(self.training, p.training), 'published': None, 'measures': False,
            'reward_variant': p.reward_variant})


class ExplorationConfig(Strict):
    biased: bool
    epsilon_start: Probability
    epsilon_end: Probability
    epsilon_decay_episodes: PositiveInt
    epsilon_decay_steps: PositiveInt | None = None   # given: the decay runs over this many RL decisions instead
    keep_lane_probability: Probability
    acceleration_std: NonNegativeFloat
    #: greedy: explore around the network's greedy choice; prior (options only): around the
    #: prior's option (``driving.prior``), the data one step of improvement over it needs
    around: Literal['greedy', 'prior'] = 'greedy'


class DemonstrationConfig(Strict):
    episodes: Count
    batch_share: Annotated[float, Field(ge=0, lt=1)]
    margin: NonNegativeFloat
    margin_weight_start: NonNegativeFloat
    margin_weight_end: NonNegativeFloat
    margin_decay_episodes: PositiveInt
    margin_decay_steps: PositiveInt | None = None   # given: the decay runs over this many RL decisions instead
    pretrain_updates: Count


#: a method run as published learns from its own experience alone
NO_DEMONSTRATIONS = {'episodes': 0, 'pretrain_updates': 0, 'batch_share': 0.0, 'margin_weight_start': 0.0,
                     'margin_weight_end': 0.0}


class ValidationConfig(Strict):
    every_episodes: PositiveInt
    episodes: PositiveInt
    min_exit_rate: UnitInterval
    max_cav_collision_rate: UnitInterval
    parallel: bool


class ActorsConfig(Strict):
    """``train --actors N``: collection on Ray actors, one learner (``learning/actors.py``)."""
    broadcast_every: PositiveInt = 50    # the learner sends its weights to the actors every this many updates
    epsilon_spread: NonNegativeFloat = 1.0   # actor i of N explores at epsilon^(1 + spread * i / (N - 1)) (Ape-X)
    max_restarts: Count = 3              # an actor whose process dies is restarted this often, then dropped


class ConditioningConfig(Strict):
    modes: list[str]
    exact_share: Probability
    concentration: PositiveFloat
    validation_modes: list[str]


class TrainingConfig(Strict):
    episodes: PositiveInt
    #: given: the RL phase's budget in environment steps (decisions) instead of ``episodes``; it
    #: ends with the episode in which the budget is reached (methods whose episodes last longer
    #: or end sooner get the same experience: a fair budget across methods)
    environment_steps: PositiveInt | None = None
    gamma: UnitInterval
    learning_rate: PositiveFloat
    fine_tune_learning_rate: PositiveFloat
    tau: UnitInterval
    batch_size: PositiveInt
    replay_size: PositiveInt
    warmup_decisions: Count
    updates_per_decision: Count
    gradient_clip: PositiveFloat
    reward_scale: PositiveFloat
    credit: Literal['own', 'global']
    #: the option a target bootstraps on in the next state: greedy (Q-learning), or prior
    #: (options only): the prior's option, SPIBB's bootstrapping with every other option
    #: counted as rarely tried; the network then learns Q of the prior, and its greedy
    #: choice is one step of policy improvement over it
    bootstrap: Literal['greedy', 'prior'] = 'greedy'
    conditioning: ConditioningConfig
    methods: dict[str, MethodConfig]
    actors: ActorsConfig = ActorsConfig()

    @property
    def method_names(self) -> list[str]:
        """Every method: each of the file, then <name>_published for each with a published row."""
        return [*self.methods, *(name + PUBLISHED_SUFFIX for name, m in self.methods.items() if m.published)]

    def method(self, name: str) -> MethodConfig:
        base = name.removesuffix(PUBLISHED_SUFFIX)
        if name not in self.method_names:
            raise ConfigError(f'unknown method {name!r}; known: {", ".join(self.method_names)}')
        return self.methods[name] if name in self.methods else self.methods[base].as_published()

    def of_method(self, name: str) -> TrainingConfig:
        """These settings with the method's own over them (validated when the file is loaded);
        a method without our measures has no demonstrations."""
        method = self.method(name)
        override = method.training
        if not method.measures:
            override = deep_merge(override, {'demonstrations': NO_DEMONSTRATIONS})
        if not override:
            return self
        return parse(TrainingConfig, deep_merge(self.model_dump(), override), f'methods.{name}.training')
    exploration: ExplorationConfig
    demonstrations: DemonstrationConfig
    validation: ValidationConfig

"""The study's configuration: every rule of the Monte Carlo study as a named, frozen option.

Two presets (docs/paper/notes.md, decision 1):
- ``reference``: what the authors' published MATLAB code (github M-DIAB/APF, CR-BAPF* only) does: obstacles
  uniform continuous in [5, 20]^2, a cumulative list of detected obstacles, the agent's own repulsion
  J_o(r) = 0 (``agent_repulsion=False``) and a single-draw random walk.
- ``paper``: what the paper's text says: obstacles uniform over the 30 m x 30 m square, only the obstacles in
  sensor range now, J_a(r) = J_t(r) + J_o(r) (Eq. (4)) and the random walk q ~ U{Q} over safe points.

Shared by both (paper Section "Simulation Setup" and docs/paper/notes.md, decision 2): start (3, 3) m, target
(22, 22) m, sensor range 8 m, step 0.4 m, N_b = 60, position noise N(0, 0.1^2) per axis on every move, collision within
0.25 m of an obstacle (checked at the start of each iteration), success within 0.7 m of the target, at most 900
iterations.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass

from apf_companion.errors import ConfigError
from apf_companion.planning import ALL_PLANNER_NAMES, PlannerParams, Preset


class DetectionRule(enum.Enum):
    """Which obstacles the planner knows at an iteration."""

    CUMULATIVE = "cumulative"
    """Every obstacle ever within sensor range stays known (the authors' code)."""
    IN_RANGE = "in-range"
    """Only the obstacles within sensor range at the current position (the paper's text)."""


class ObstacleSampling(enum.Enum):
    """How obstacle coordinates are drawn inside ``obstacle_box_m``."""

    CONTINUOUS = "continuous"
    """Uniform continuous on every axis (docs/paper/notes.md: both presets)."""
    INTEGER = "integer"
    """Uniform over the integer coordinates of the box, like the authors' README example
    ``Bacteria_Run(randi([5 20], [50, 2]))``; repeated points count once (their detection merges duplicates)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Density:
    """Obstacle count N ~ discrete U[n_low, n_high], inclusive, redrawn per trial (docs/paper/notes.md, decision 5)."""

    n_low: int
    n_high: int

    def __post_init__(self) -> None:
        if not 0 <= self.n_low <= self.n_high:
            msg = f"density: need 0 <= n_low <= n_high, got n_low={self.n_low}, n_high={self.n_high}"
            raise ConfigError(msg)

    @property
    def label(self) -> str:
        return f"{self.n_low}-{self.n_high}"

    @classmethod
    def parse(cls, text: str) -> Density:
        """Parse ``"20-45"`` (or a single count ``"50"``)."""
        parts = text.strip().split("-")
        try:
            values = [int(p) for p in parts]
        except ValueError as err:
            msg = f"density: expected LOW-HIGH obstacle counts like 20-45, got {text!r}"
            raise ConfigError(msg) from err
        if len(values) == 1:
            return cls(n_low=values[0], n_high=values[0])
        if len(values) != 2:
            msg = f"density: expected LOW-HIGH obstacle counts like 20-45, got {text!r}"
            raise ConfigError(msg)
        return cls(n_low=values[0], n_high=values[1])


DEFAULT_DENSITIES: tuple[Density, ...] = (
    Density(n_low=20, n_high=45),
    Density(n_low=45, n_high=70),
    Density(n_low=70, n_high=95),
)
"""The paper's three densities (Table II a-c)."""

PRESET_NAMES: tuple[str, ...] = (Preset.REFERENCE.value, Preset.PAPER.value)  # the study's two presets


def _pair(values: tuple[float, ...], name: str) -> None:
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        msg = f"{name}: need 2 or 3 finite coordinates, got {values!r}"
        raise ConfigError(msg)


@dataclass(frozen=True, slots=True, kw_only=True)
class StudyConfig:
    """All rules of one Monte Carlo study. Build with ``StudyConfig.reference()`` / ``.paper()``, vary with
    ``dataclasses.replace``.

    The planner-side rules (agent repulsion, random-walk rule, mu_o, ...) live in ``planner_params``.
    """

    preset: str
    """Name of the preset this configuration came from (informational)."""
    planner_params: PlannerParams
    obstacle_box_m: tuple[float, float]
    """Obstacles are uniform continuous in [low, high] on every axis [m]."""
    detection: DetectionRule
    obstacle_sampling: ObstacleSampling = ObstacleSampling.CONTINUOUS
    start_m: tuple[float, ...] = (3.0, 3.0)
    target_m: tuple[float, ...] = (22.0, 22.0)
    sensor_range_m: float = 8.0
    """An obstacle is detected when at most this far from the agent [m] (inclusive, as the authors' code)."""
    noise_std_m: float = 0.1
    """Standard deviation of the position error added per axis on every move [m]."""
    collision_radius_m: float = 0.25
    """Collision when strictly closer than this to an obstacle at the start of an iteration [m]."""
    goal_radius_m: float = 0.7
    """Success when at most this far from the target at the start of an iteration [m]."""
    max_iterations: int = 900
    """Iteration cap; a trial still running after it is a timeout."""
    capf_patience: int = 60
    """CAPF is stuck after this many iterations without a new best distance to the target (or at once when
    its gradient vanishes; docs/paper/notes.md, CAPF)."""
    chunk_trials: int = 500
    """Trials per seeded chunk. Part of the random-stream layout: change it and the draws change."""

    def __post_init__(self) -> None:
        _pair(self.start_m, "start_m")
        _pair(self.target_m, "target_m")
        if len(self.start_m) != len(self.target_m) or len(self.start_m) != self.planner_params.dim:
            msg = (
                f"start_m/target_m: need {self.planner_params.dim} coordinates (planner_params.dim), "
                f"got {len(self.start_m)} and {len(self.target_m)}"
            )
            raise ConfigError(msg)
        low, high = self.obstacle_box_m
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            msg = f"obstacle_box_m: need finite low < high, got {self.obstacle_box_m!r}"
            raise ConfigError(msg)
        for name in ("sensor_range_m", "collision_radius_m", "goal_radius_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                msg = f"{name}: need a finite value > 0, got {value!r}"
                raise ConfigError(msg)
        if not (math.isfinite(self.noise_std_m) and self.noise_std_m >= 0.0):
            msg = f"noise_std_m: need a finite value >= 0, got {self.noise_std_m!r}"
            raise ConfigError(msg)
        if self.max_iterations < 1:
            msg = f"max_iterations: need >= 1, got {self.max_iterations}"
            raise ConfigError(msg)
        if self.capf_patience < 1:
            msg = f"capf_patience: need >= 1, got {self.capf_patience}"
            raise ConfigError(msg)
        if self.chunk_trials < 1:
            msg = f"chunk_trials: need >= 1, got {self.chunk_trials}"
            raise ConfigError(msg)

    @property
    def dim(self) -> int:
        return len(self.start_m)

    @classmethod
    def reference(cls) -> StudyConfig:
        """The authors' code (docs/paper/notes.md): obstacles in [5, 20]^2, cumulative detection, J_o(r) = 0,
        single-draw random walk (all through ``PlannerParams.reference()``)."""
        return cls(
            preset="reference",
            planner_params=PlannerParams.reference(),
            obstacle_box_m=(5.0, 20.0),
            detection=DetectionRule.CUMULATIVE,
        )

    @classmethod
    def paper(cls) -> StudyConfig:
        """The paper's text: obstacles over [0, 30]^2, in-range detection, agent repulsion on, random walk
        over the safe set (``PlannerParams.paper()``)."""
        return cls(
            preset="paper",
            planner_params=PlannerParams.paper(),
            obstacle_box_m=(0.0, 30.0),
            detection=DetectionRule.IN_RANGE,
        )

    @classmethod
    def from_preset(cls, name: str) -> StudyConfig:
        makers = {Preset.REFERENCE: cls.reference, Preset.PAPER: cls.paper}
        if name not in PRESET_NAMES:
            msg = f"preset: unknown {name!r}; choose one of {', '.join(PRESET_NAMES)}"
            raise ConfigError(msg)
        return makers[Preset(name)]()

    def with_mu_o(self, mu_o_per_m2: float) -> StudyConfig:
        """The same study with another obstacle decay rate mu_o (the paper's R_s-vs-mu_o figure)."""
        params = dataclasses.replace(self.planner_params, mu_o_per_m2=float(mu_o_per_m2))
        return dataclasses.replace(self, planner_params=params)


def check_planner_names(names: tuple[str, ...]) -> tuple[str, ...]:
    """Validate planner names against ``ALL_PLANNER_NAMES`` (the paper's five, bapf-nav, bendyruler)."""
    for name in names:
        if name not in ALL_PLANNER_NAMES:
            msg = f"planners: unknown {name!r}; choose from {', '.join(ALL_PLANNER_NAMES)}"
            raise ConfigError(msg)
    return names


def mu_sweep_grid() -> tuple[float, ...]:
    """The paper's mu_o grid for the R_s-vs-mu_o figure: 1000 k / 12, k = 0..12, with 1 for k = 0."""
    return tuple(1.0 if k == 0 else 1000.0 * k / 12.0 for k in range(13))

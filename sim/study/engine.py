"""Lockstep batched Monte Carlo engine for the paper's study.

Thousands of trials advance together as one array program: positions are ``(A, D)``, obstacle fields are padded
to ``(A, N_max, D)`` with masks, the planner decides for every active trial in one ``step_batch`` call, and
finished trials leave the active set (its arrays are compacted in place).

One iteration of a trial, in the authors' order (docs/paper/notes.md; github M-DIAB/APF ``Bacteria_Run.m``):

1. count the iteration (M_s counts iterations, including ones without a move);
2. collision: closer than ``collision_radius_m`` to any obstacle -> COLLISION;
3. detection: obstacles within ``sensor_range_m`` become known (``DetectionRule``), and the minimum distance
   of every obstacle to the visited positions is updated (for S, Eq. (16));
4. goal: within ``goal_radius_m`` of the target -> SUCCESS (this is the "one final extra iteration after
   entering the goal circle": the move that would follow cannot change any metric, so it is not computed);
5. stuck rules: CAPF without a new best target distance for ``capf_patience`` iterations -> STUCK;
6. plan: ``planner.step_batch`` on the known obstacles. A LOCAL_MINIMUM ends BAPF, CR-BAPF and A-BAPF
   (docs/paper/notes.md, decision 3), CAPF (vanishing gradient) and the bendyruler baseline (nothing changes
   until it moves); for CR-BAPF* it ends the trial only under the SAFE_SET random walk (an empty safe set is a fixed
   point), while under SINGLE_DRAW it is a no-move iteration; for bapf-nav it is a no-move iteration, and its
   GAVE_UP (the planner's own give-up rule) is STUCK. Stateful planners (``StatefulPlanner``) get their
   per-trial state, which follows the trials through the compaction;
7. move: next point plus N(0, noise_std_m^2) per axis; no move, no noise.

A trial still running after ``max_iterations`` is a TIMEOUT.

Determinism: trials are split into fixed chunks of ``config.chunk_trials``. The generators of chunk ``c`` of
density [N_l, N_u] come from ``SeedSequence(seed, spawn_key=(N_l, N_u, c))`` (two children: worlds, motion), so a
chunk's result depends only on (config, planner, density, chunk, seed), never on the worker that ran it or on
which other chunks ran. Worlds and noise streams do not depend on the planner: every planner and every mu_o of
the sweep sees the same obstacle fields (common random numbers).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from apf_companion.planning import (
    AgentState,
    BatchDecision,
    DecisionReason,
    PlannerName,
    RandomWalkRule,
    get_planner,
)
from sim.study import _worker
from sim.study.config import Density, DetectionRule, StudyConfig
from sim.study.metrics import Outcome, TrialRecords, safety_per_trial
from sim.study.worlds import WorldBatch, draw_worlds

log = logging.getLogger(__name__)

_RUNNING = -1
_T = TypeVar("_T")

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


class BatchPlanner(Protocol):
    """What the engine needs of a planner (``apf_companion.planning.Planner`` satisfies it)."""

    def step_batch(
        self,
        positions_m: FloatArray,
        targets_m: FloatArray,
        obstacles_m: FloatArray,
        obstacle_mask: BoolArray,
        rng: np.random.Generator | None = None,
    ) -> BatchDecision: ...


NoiseFn = Callable[[npt.NDArray[np.intp], int], FloatArray]
"""(trial ids of this iteration's movers, ascending; D) -> (movers, D) position noise [m]."""

ClearanceFn = Callable[[FloatArray, FloatArray], FloatArray]
"""(A, D) segment starts, (A, D) ends -> (A,) smallest distance from each straight segment to the TRUE obstacle
surfaces [m] (a point when start = end): world files, whose walls and cylinders the planners see only as surface
sample points (``sim.study.worldstudy``)."""

_STOPS_AT_LOCAL_MINIMUM = frozenset(
    {PlannerName.CAPF, PlannerName.BAPF, PlannerName.A_BAPF, PlannerName.CR_BAPF, PlannerName.BENDYRULER}
)
"""Planners whose trial ends at the first LOCAL_MINIMUM (docs/paper/notes.md, decision 3; CAPF: vanishing
gradient)."""


def stops_at_local_minimum(planner_name: str, config: StudyConfig) -> bool:
    """Whether a LOCAL_MINIMUM decision ends a trial of ``planner_name`` (see module docstring, step 6)."""
    if planner_name in _STOPS_AT_LOCAL_MINIMUM:
        return True
    if planner_name == PlannerName.BAPF_NAV:
        return False
    return config.planner_params.random_walk == RandomWalkRule.SAFE_SET


@dataclass(frozen=True, slots=True, kw_only=True)
class Trace:
    """Per-iteration history of a small batch (for figures). Rows of finished trials are NaN."""

    positions_m: FloatArray
    """(T, A, D) position at the start of each iteration [m]."""
    reason: npt.NDArray[np.int8]
    """(T, A) DecisionReason code of each iteration (-1: no decision, e.g. the trial ended there)."""
    mu_o_k: FloatArray
    """(T, A) A-BAPF's mu_o,k of the chosen point (NaN for other planners or no move)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class SimulationResult:
    records: TrialRecords
    trace: Trace | None
    detected: BoolArray
    """(A, N_max) obstacles detected during each run."""


@dataclass(slots=True)
class _Outputs:
    """Per-trial outputs of ``simulate``, indexed by trial id."""

    outcome: npt.NDArray[np.int8]
    iterations: npt.NDArray[np.int32]
    detected: BoolArray
    min_dist: FloatArray
    path: FloatArray
    clear: FloatArray
    swept: FloatArray
    """Clearance of the move that led to each trial's position [m]."""

    @classmethod
    def empty(cls, n_trials: int, n_max: int) -> _Outputs:
        return cls(
            outcome=np.full(n_trials, _RUNNING, dtype=np.int8),
            iterations=np.zeros(n_trials, dtype=np.int32),
            detected=np.zeros((n_trials, n_max), dtype=bool),
            min_dist=np.full((n_trials, n_max), np.inf),
            path=np.zeros(n_trials),
            clear=np.full(n_trials, np.inf),
            swept=np.full(n_trials, np.inf),
        )


@dataclass(slots=True)
class _Active:
    """The active set's arrays, row i = trial ``ids[i]`` (compacted when trials finish)."""

    ids: npt.NDArray[np.intp]
    pos: FloatArray
    obs: FloatArray
    obs_raw: FloatArray
    ever: BoolArray
    min_dist: FloatArray
    best_goal_dist: FloatArray
    since_best: npt.NDArray[np.int32]
    state: AgentState | None

    def retire(self, finished: npt.NDArray[np.int8], out: _Outputs) -> None:
        """Record the finished trials' outcomes and drop them from the active set."""
        done = finished != _RUNNING
        if not done.any():
            return
        done_ids = self.ids[done]
        out.outcome[done_ids] = finished[done]
        out.detected[done_ids] = self.ever[done]
        out.min_dist[done_ids] = self.min_dist[done]
        keep = ~done
        self.ids = self.ids[keep]
        self.pos = self.pos[keep]
        self.obs = self.obs[keep]
        self.obs_raw = self.obs_raw[keep]
        self.ever = self.ever[keep]
        self.min_dist = self.min_dist[keep]
        self.best_goal_dist = self.best_goal_dist[keep]
        self.since_best = self.since_best[keep]
        if self.state is not None:
            self.state = self.state.take(keep)


@dataclass(slots=True)
class _Tracer:
    """The per-iteration ``Trace`` of a recorded run."""

    n_trials: int
    dim: int
    pos: list[FloatArray]
    reason: list[npt.NDArray[np.int8]]
    mu: list[FloatArray]

    def frame(self, ids: npt.NDArray[np.intp], pos: FloatArray) -> None:
        frame = np.full((self.n_trials, self.dim), np.nan)
        frame[ids] = pos
        self.pos.append(frame)
        self.reason.append(np.full(self.n_trials, -1, dtype=np.int8))
        self.mu.append(np.full(self.n_trials, np.nan))

    def decisions(self, rows: npt.NDArray[np.intp], bd: BatchDecision) -> None:
        self.reason[-1][rows] = np.asarray(bd.reason)
        self.mu[-1][rows] = np.asarray(bd.mu_o_k, dtype=np.float64)

    def trace(self) -> Trace:
        n, d = self.n_trials, self.dim
        return Trace(
            positions_m=np.stack(self.pos) if self.pos else np.zeros((0, n, d)),
            reason=np.stack(self.reason) if self.reason else np.zeros((0, n), np.int8),
            mu_o_k=np.stack(self.mu) if self.mu else np.zeros((0, n)),
        )


def simulate(
    config: StudyConfig,
    planner_name: str,
    worlds: WorldBatch,
    rng: np.random.Generator,
    *,
    record: bool = False,
    planner: BatchPlanner | None = None,
    clearance: ClearanceFn | None = None,
    noise: NoiseFn | None = None,
) -> SimulationResult:
    """Run A trials of ``planner_name`` in lockstep on the given obstacle fields.

    Parameters
    ----------
    config : study rules.
    planner_name : one of ``apf_companion.planning.PLANNER_NAMES``.
    worlds : (A, N_max, D) obstacle fields with masks.
    rng : motion generator (random walk draws inside the planner, position noise here).
    record : keep the per-iteration ``Trace`` (memory O(max_iterations * A); for small batches only).
    planner : use this planner object instead of ``get_planner(planner_name, config.planner_params)``
        (instrumented planners in tests and benchmarks; ``planner_name`` still selects the stop rules).
    clearance : the true geometry's clearance (world files): collisions are judged on it, swept along each move
        (a thin wall cannot be stepped through), instead of on the distance to the obstacle points at the start
        of each iteration, and it is the recorded clearance. Default: the points are the truth.
    noise : the movers' position noise (``run_group``: each chunk's trials from that chunk's generator). Default:
        N(0, noise_std_m^2) per axis from ``rng``, the movers in trial order.

    Returns
    -------
    SimulationResult with per-trial records (``time_ms`` is zero here; ``run_chunk`` fills it in).
    """
    if planner is None:
        planner = get_planner(planner_name, config.planner_params)
    stop_at_minimum = stops_at_local_minimum(planner_name, config)
    raw = np.asarray(worlds.obstacles_m, dtype=np.float64)
    n_trials, n_max, dim = raw.shape
    exists = np.asarray(worlds.mask, dtype=bool)
    out = _Outputs.empty(n_trials, n_max)
    act = _initial_active(config, planner, raw, exists)
    targets = np.broadcast_to(np.asarray(config.target_m, dtype=np.float64), (n_trials, dim))
    tracer = _Tracer(n_trials, dim, [], [], []) if record else None
    if noise is None:
        noise = _normal_noise(config, rng)
    loop = _Loop(config, planner, planner_name == "capf", stop_at_minimum, targets, rng, noise, clearance, tracer)
    for it in range(1, config.max_iterations + 1):
        if act.ids.size == 0:
            break
        loop.iteration(it, act, out)
    act.retire(np.full(act.ids.size, Outcome.TIMEOUT, dtype=np.int8), out)
    trace = None if tracer is None else tracer.trace()
    return SimulationResult(records=_records(out, exists, clearance), trace=trace, detected=out.detected)


@dataclass(frozen=True, slots=True)
class _Loop:
    """What one lockstep iteration of ``simulate`` needs besides the active set and the outputs."""

    config: StudyConfig
    planner: BatchPlanner
    is_capf: bool
    stop_at_minimum: bool
    targets: FloatArray
    rng: np.random.Generator
    noise: NoiseFn
    clearance: ClearanceFn | None
    tracer: _Tracer | None

    def iteration(self, it: int, act: _Active, out: _Outputs) -> None:
        """Steps 1-7 of the study's loop for the active trials (the module docstring's numbering)."""
        out.iterations[act.ids] = it  # 1. count
        if self.tracer is not None:
            self.tracer.frame(act.ids, act.pos)
        finished, in_range = _sense(self.config, act, out, self.clearance, is_capf=self.is_capf)  # 2.-5.
        planning = finished == _RUNNING
        if planning.any():  # 6.-7.
            sel = np.flatnonzero(planning)
            bd = _plan(self.config, self.planner, act, sel, self.targets, in_range, self.rng)
            if self.tracer is not None:
                self.tracer.decisions(act.ids[sel], bd)
            _stop_rules(bd, sel, finished, stop_at_minimum=self.stop_at_minimum)
            _move(act, out, bd, sel, finished, self.noise, self.clearance)
        act.retire(finished, out)


def _records(out: _Outputs, exists: BoolArray, clearance: ClearanceFn | None) -> TrialRecords:
    """The per-trial records of a finished run (``time_ms`` zero)."""
    n_trials = out.outcome.size
    return TrialRecords(
        outcome=out.outcome,
        iterations=out.iterations,
        safety_m=safety_per_trial(out.min_dist, out.detected),
        n_obstacles=exists.sum(axis=1).astype(np.int32),
        n_detected=out.detected.sum(axis=1).astype(np.int32),
        time_ms=np.zeros(n_trials),
        path_m=out.path,
        clearance_m=out.clear if clearance is not None else out.min_dist.min(axis=1, initial=np.inf),
    )


def _initial_active(config: StudyConfig, planner: BatchPlanner, raw: FloatArray, exists: BoolArray) -> _Active:
    """Every trial at the start, nothing detected yet."""
    n_trials, n_max, dim = raw.shape
    # Padding rows sit at infinity, so distances to them are +inf and never detected or collided with.
    padded = np.where(exists[..., None], raw, np.inf)
    start = np.asarray(config.start_m, dtype=np.float64)
    # Stateful planners (``StatefulPlanner``, or a wrapper that forwards ``initial_state``) get per-trial state.
    state: AgentState | None = planner.initial_state(n_trials) if hasattr(planner, "initial_state") else None
    return _Active(
        ids=np.arange(n_trials),
        pos=np.broadcast_to(start, (n_trials, dim)).copy(),
        obs=padded.copy(),
        obs_raw=raw.copy(),
        ever=np.zeros((n_trials, n_max), dtype=bool),
        min_dist=np.full((n_trials, n_max), np.inf),
        best_goal_dist=np.full(n_trials, np.inf),
        since_best=np.zeros(n_trials, dtype=np.int32),
        state=state,
    )


def _sense(
    config: StudyConfig, act: _Active, out: _Outputs, clearance: ClearanceFn | None, *, is_capf: bool
) -> tuple[npt.NDArray[np.int8], BoolArray]:
    """Steps 2-5 (collision, detection, goal, CAPF's stuck rule): each active trial's outcome so far
    (``_RUNNING`` = plan on) and the obstacles in sensor range."""
    target = np.asarray(config.target_m, dtype=np.float64)
    pos = act.pos
    dist = _distances(act.obs, pos)
    if clearance is None:
        collided = (dist < config.collision_radius_m).any(axis=1)
    else:
        true_clear = np.minimum(clearance(pos, pos), out.swept[act.ids])
        out.clear[act.ids] = np.minimum(out.clear[act.ids], true_clear)
        collided = true_clear < config.collision_radius_m
    in_range = dist <= config.sensor_range_m
    act.ever |= in_range
    np.minimum(act.min_dist, dist, out=act.min_dist)
    goal_dist = np.sqrt(np.einsum("ad,ad->a", pos - target, pos - target))
    reached = ~collided & (goal_dist <= config.goal_radius_m)

    finished = np.full(act.ids.size, _RUNNING, dtype=np.int8)
    finished[collided] = Outcome.COLLISION
    finished[reached] = Outcome.SUCCESS
    if is_capf:
        improved = goal_dist < act.best_goal_dist
        act.best_goal_dist = np.where(improved, goal_dist, act.best_goal_dist)
        act.since_best = np.where(improved, 0, act.since_best + 1).astype(np.int32)
        finished[(finished == _RUNNING) & (act.since_best >= config.capf_patience)] = Outcome.STUCK
    return finished, in_range


def _distances(obstacles_m: FloatArray, positions_m: FloatArray) -> FloatArray:
    """(A, N) distance from each agent to each of its obstacles [m].

    2D: the two coordinate planes, dx^2 + dy^2, which is einsum's sum of the two products bit for bit and about 5x
    faster (einsum over a short last axis is slow; measured at (500, 95, 2): 842 vs 167 us). 3D keeps einsum,
    whose order of the three terms is its own."""
    if obstacles_m.shape[2] == 2:
        dx = obstacles_m[:, :, 0] - positions_m[:, 0, None]
        dy = obstacles_m[:, :, 1] - positions_m[:, 1, None]
        dx *= dx
        dy *= dy
        dx += dy
        return np.sqrt(dx, out=dx)
    diff = obstacles_m - positions_m[:, None, :]
    return np.asarray(np.sqrt(np.einsum("and,and->an", diff, diff)), dtype=np.float64)


def _plan(
    config: StudyConfig,
    planner: BatchPlanner,
    act: _Active,
    sel: npt.NDArray[np.intp],
    targets: FloatArray,
    in_range: BoolArray,
    rng: np.random.Generator,
) -> BatchDecision:
    """Step 6: the planner's decisions for the planning rows ``sel`` of the active set, on the known obstacles
    (every one detected so far under ``DetectionRule.CUMULATIVE``, else those in sensor range now)."""
    known = act.ever if config.detection == DetectionRule.CUMULATIVE else in_range
    a = act.ids.size
    if act.state is not None:
        return _step_stateful(planner, act.state, sel, a, act.pos, targets, act.obs_raw, known)
    if sel.size == a:  # the usual case: no gather copies
        return planner.step_batch(act.pos, targets[:a], act.obs_raw, known, rng)
    return planner.step_batch(act.pos[sel], targets[: sel.size], act.obs_raw[sel], known[sel], rng)


def _stop_rules(
    bd: BatchDecision, sel: npt.NDArray[np.intp], finished: npt.NDArray[np.int8], *, stop_at_minimum: bool
) -> None:
    """Step 6's ends: LOCAL_MINIMUM (for the planners it stops) and GAVE_UP are STUCK."""
    reason = np.asarray(bd.reason)
    if stop_at_minimum:
        finished[sel[reason == DecisionReason.LOCAL_MINIMUM]] = Outcome.STUCK
    finished[sel[reason == DecisionReason.GAVE_UP]] = Outcome.STUCK


def _normal_noise(config: StudyConfig, rng: np.random.Generator) -> NoiseFn:
    """N(0, noise_std_m^2) per axis for every mover, in trial order, from one generator."""

    def noise(ids: npt.NDArray[np.intp], dim: int) -> FloatArray:
        return rng.normal(0.0, config.noise_std_m, size=(ids.size, dim))

    return noise


def _move(
    act: _Active,
    out: _Outputs,
    bd: BatchDecision,
    sel: npt.NDArray[np.intp],
    finished: npt.NDArray[np.int8],
    noise: NoiseFn,
    clearance: ClearanceFn | None,
) -> None:
    """Step 7: still-running trials with a next point move there plus the position noise."""
    next_pts = np.asarray(bd.next_points_m, dtype=np.float64)
    moves = ~np.isnan(next_pts[:, 0]) & (finished[sel] == _RUNNING)
    if not moves.any():
        return
    pos = act.pos
    movers = sel[moves]
    new_pos = next_pts[moves] + noise(act.ids[movers], pos.shape[1])
    if clearance is not None:
        out.swept[act.ids[movers]] = clearance(pos[movers], new_pos)
    out.path[act.ids[movers]] += np.sqrt(np.einsum("ad,ad->a", new_pos - pos[movers], new_pos - pos[movers]))
    pos[movers] = new_pos


def _step_stateful(
    planner: Any,
    state: AgentState,
    sel: npt.NDArray[np.intp],
    a: int,
    pos: FloatArray,
    targets: FloatArray,
    obs_raw: FloatArray,
    known: BoolArray,
) -> BatchDecision:
    """``step_batch`` of a stateful planner on the planning rows ``sel`` of the ``a`` active trials."""
    if sel.size == a:
        out: BatchDecision = planner.step_batch(pos, targets[:a], obs_raw, known, state=state)
        return out
    sub = state.take(sel)
    out = planner.step_batch(pos[sel], targets[: sel.size], obs_raw[sel], known[sel], state=sub)
    state.put(sel, sub)
    return out


# --------------------------------------------------------------------------------------------- chunks


@dataclass(frozen=True, slots=True, kw_only=True)
class ChunkTask:
    """One fixed, seeded chunk of trials: everything a worker needs (picklable)."""

    config: StudyConfig
    planner_name: str
    density: Density
    chunk_index: int
    n_trials: int
    seed: int


@dataclass(frozen=True, slots=True, kw_only=True)
class ChunkResult:
    task: ChunkTask
    records: TrialRecords
    wall_s: float
    cpu_s: float = 0.0
    """The worker's CPU time for the chunk [s] (``time.process_time``): unlike ``wall_s``, not stretched by other
    processes sharing the cores. A chunk of a ``ChunkGroup`` gets the group's in proportion to its iterations."""


def chunk_generators(seed: int, density: Density, chunk_index: int) -> tuple[np.random.Generator, ...]:
    """(worlds, motion) generators of one chunk; independent of planner, worker and other chunks."""
    seq = np.random.SeedSequence(seed, spawn_key=(density.n_low, density.n_high, chunk_index))
    return tuple(np.random.default_rng(child) for child in seq.spawn(2))


def chunk_worlds(task: ChunkTask) -> WorldBatch:
    world_rng, _ = chunk_generators(task.seed, task.density, task.chunk_index)
    cfg = task.config
    return draw_worlds(world_rng, task.n_trials, task.density, cfg.obstacle_box_m, cfg.dim, cfg.obstacle_sampling)


def run_chunk(task: ChunkTask) -> ChunkResult:
    """Run one chunk (top-level so process pools can pickle it)."""
    t0, c0 = time.perf_counter(), time.process_time()
    world_rng, motion_rng = chunk_generators(task.seed, task.density, task.chunk_index)
    cfg = task.config
    worlds = draw_worlds(world_rng, task.n_trials, task.density, cfg.obstacle_box_m, cfg.dim, cfg.obstacle_sampling)
    result = simulate(cfg, task.planner_name, worlds, motion_rng)
    wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
    return ChunkResult(task=task, records=_timed(result.records, wall_s), wall_s=wall_s, cpu_s=cpu_s)


def _timed(rec: TrialRecords, wall_s: float) -> TrialRecords:
    """``rec`` with ``time_ms``: lockstep trials share every array operation, so the wall time of their run is
    split in proportion to the iterations each trial ran (the mean is wall time / trials either way)."""
    weights = rec.iterations / max(int(rec.iterations.sum()), 1)
    return TrialRecords(
        outcome=rec.outcome,
        iterations=rec.iterations,
        safety_m=rec.safety_m,
        n_obstacles=rec.n_obstacles,
        n_detected=rec.n_detected,
        time_ms=1e3 * wall_s * weights,
        path_m=rec.path_m,
        clearance_m=rec.clearance_m,
    )


FUSED_PLANNERS = frozenset({PlannerName.BENDYRULER})
"""Planners whose chunks of one cell run as one lockstep batch (``ChunkGroup``). bendyruler's study has a long tail:
at 70-95 obstacles about 750 of a chunk's 900 iterations step the 10-50 trials that cycle until they time out,
each iteration a fixed numpy cost, which eight chunks together pay once. Only stateful planners qualify (they get
no generator, so each chunk's noise stream is the only draw) whose rows decide independently of each other."""

FUSED_CHUNKS = 8
"""Chunks per ``ChunkGroup`` at most (a whole default cell of 4000 trials)."""


@dataclass(frozen=True, slots=True)
class ChunkGroup:
    """Consecutive chunks of one (config, planner, density, seed) run together by ``run_group``; each chunk's
    result equals ``run_chunk``'s (its own worlds and noise stream, rows that decide independently), only the
    timing is shared."""

    tasks: tuple[ChunkTask, ...]

    @property
    def n_trials(self) -> int:
        return sum(t.n_trials for t in self.tasks)


def group_tasks(tasks: Sequence[ChunkTask]) -> list[ChunkGroup]:
    """``tasks`` in order, runs of up to ``FUSED_CHUNKS`` chunks of one cell of a ``FUSED_PLANNERS`` planner as one
    group, every other chunk alone."""
    groups: list[list[ChunkTask]] = []
    for t in tasks:
        last = groups[-1][-1] if groups else None
        joins = (
            last is not None
            and t.planner_name in FUSED_PLANNERS
            and len(groups[-1]) < FUSED_CHUNKS
            and (t.config, t.planner_name, t.density, t.seed)
            == (last.config, last.planner_name, last.density, last.seed)
        )
        if joins:
            groups[-1].append(t)
        else:
            groups.append([t])
    return [ChunkGroup(tuple(g)) for g in groups]


def run_group(group: ChunkGroup) -> list[ChunkResult]:
    """Run a ``ChunkGroup``'s chunks in one lockstep batch (top-level so process pools can pickle it)."""
    tasks = group.tasks
    if len(tasks) == 1:
        return [run_chunk(tasks[0])]
    t0, c0 = time.perf_counter(), time.process_time()
    cfg, name = tasks[0].config, tasks[0].planner_name
    worlds, rngs = [], []
    for t in tasks:
        world_rng, motion_rng = chunk_generators(t.seed, t.density, t.chunk_index)
        worlds.append(draw_worlds(world_rng, t.n_trials, t.density, cfg.obstacle_box_m, cfg.dim, cfg.obstacle_sampling))
        rngs.append(motion_rng)
    batch = WorldBatch(
        obstacles_m=np.concatenate([w.obstacles_m for w in worlds]), mask=np.concatenate([w.mask for w in worlds])
    )
    starts = np.cumsum([0] + [t.n_trials for t in tasks])
    result = simulate(cfg, name, batch, rngs[0], noise=_chunk_noise(cfg, rngs, starts))
    wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
    rec = _timed(result.records, wall_s)
    out = []
    for i, t in enumerate(tasks):
        part = rec.rows(int(starts[i]), int(starts[i + 1]))
        part_wall_s = 1e-3 * float(part.time_ms.sum())
        share = part_wall_s / wall_s if wall_s > 0.0 else 0.0
        out.append(ChunkResult(task=t, records=part, wall_s=part_wall_s, cpu_s=cpu_s * share))
    return out


def _chunk_noise(config: StudyConfig, rngs: Sequence[np.random.Generator], starts: npt.NDArray[np.intp]) -> NoiseFn:
    """Chunk c's movers (trial ids [starts[c], starts[c + 1])) draw from chunk c's generator, in trial order: the
    same draws as the chunk alone, whose movers they are."""

    def noise(ids: npt.NDArray[np.intp], dim: int) -> FloatArray:
        out = np.empty((ids.size, dim))
        cuts = np.searchsorted(ids, starts)
        for c, rng in enumerate(rngs):
            lo, hi = int(cuts[c]), int(cuts[c + 1])
            if hi > lo:  # alone, a chunk without movers draws nothing
                out[lo:hi] = rng.normal(0.0, config.noise_std_m, size=(hi - lo, dim))
        return out

    return noise


def make_tasks(
    config: StudyConfig,
    planners: Sequence[str],
    densities: Sequence[Density],
    trials: int,
    seed: int,
) -> list[ChunkTask]:
    """Split ``trials`` per (planner, density) into fixed chunks of ``config.chunk_trials``."""
    tasks: list[ChunkTask] = []
    for planner_name in planners:
        for density in densities:
            for c, start in enumerate(range(0, trials, config.chunk_trials)):
                n = min(config.chunk_trials, trials - start)
                tasks.append(
                    ChunkTask(
                        config=config,
                        planner_name=planner_name,
                        density=density,
                        chunk_index=c,
                        n_trials=n,
                        seed=seed,
                    )
                )
    return tasks


# ------------------------------------------------------------------------------------------ executors


class SerialExecutor(Executor):
    """Runs each task at submit time in the calling thread (``--workers 1``, tests, debugging)."""

    def submit(self, fn: Callable[..., _T], /, *args: Any, **kwargs: Any) -> Future[_T]:
        future: Future[_T] = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as err:  # delivered through the future, like other executors
            future.set_exception(err)
        return future


@contextlib.contextmanager
def _single_thread_blas_env() -> Iterator[None]:
    """Spawned workers inherit the environment at creation time: limit BLAS threads while they start."""
    saved = {name: os.environ.get(name) for name in _worker._SINGLE_THREAD_ENV}
    _worker.init()
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def default_executor(workers: int | None = None) -> Executor:
    """``SerialExecutor`` for one worker, else a ``ProcessPoolExecutor`` (default: all cores) whose workers start
    by ``start_method()``."""
    n = workers if workers is not None else (os.cpu_count() or 1)
    if n <= 1:
        return SerialExecutor()
    context = multiprocessing.get_context(start_method())
    return ProcessPoolExecutor(max_workers=n, mp_context=context, initializer=_worker.init)


def start_method() -> str:
    """ "fork" where this process runs a single thread, else "spawn".

    A forked worker starts with the modules this process has imported: about 0.3 s less before the first chunk
    of a study than spawned workers that import numpy, scipy and the planners again (measured on the 2-core
    machine: 0.06 s against 0.31 s for a pool's first results). Forking a process that runs other threads can
    deadlock a child on a lock held by one of them (Python 3.12 warns; 3.14 no longer forks by default), and
    OpenBLAS runs its own threads when ``OPENBLAS_NUM_THREADS`` is not 1, so then the workers are spawned as
    before. ``ProcessPoolExecutor`` with fork starts all its workers at the first submit, before its own
    management thread (``concurrent/futures/process.py``), so the pool itself adds no thread before the fork."""
    if "fork" not in multiprocessing.get_all_start_methods():
        return "spawn"
    return "fork" if os_thread_count() == 1 else "spawn"


def os_thread_count() -> int | None:
    """Threads of this process as the kernel counts them (native ones too: OpenBLAS, a Rust runtime), from
    /proc/self/status; None where that cannot be read (not Linux)."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Threads:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


@dataclass(frozen=True, slots=True, kw_only=True)
class CellResult:
    """All trials of one (planner, density) cell, in chunk order."""

    planner_name: str
    density: Density
    records: TrialRecords
    wall_s: float
    """Sum of the chunks' wall-clock times [s] (CPU-side cost, summed over workers)."""
    cpu_s: float = 0.0
    """Sum of the chunks' CPU times [s] (``ChunkResult.cpu_s``)."""


ProgressFn = Callable[[int, int], None]
"""Called as ``progress(trials_done, trials_total)`` after each chunk."""


def run_tasks(
    tasks: Sequence[ChunkTask],
    executor: Executor | None = None,
    *,
    workers: int | None = None,
    progress: ProgressFn | None = None,
) -> list[ChunkResult]:
    """Run chunks on ``executor`` (default: ``default_executor(workers)``, shut down afterwards), those of
    ``FUSED_PLANNERS`` in groups (``group_tasks``).

    Results come back in task order, whatever order the workers finish in.
    """
    groups = group_tasks(tasks)
    results = map_tasks(run_group, groups, executor, workers=workers, progress=progress, cost=group_cost)
    return [r for rs in results for r in rs]


_COST_PER_TRIAL: dict[str, float] = {PlannerName.BAPF_NAV: 10.0, PlannerName.BENDYRULER: 6.0}
"""Relative CPU time per trial and obstacle (the paper's planners 1), from the default study on this project's
2-core machine (per 1000 trials summed over the three densities: bapf-nav 9.8 s, bendyruler 6.7 s, the paper's
0.5-1.1 s). Only the order of the chunks depends on it, never a result."""


def group_cost(group: ChunkGroup) -> float:
    """The expected CPU time of a group (relative): trials x most obstacles x the planner's cost per trial."""
    t = group.tasks[0]
    return group.n_trials * t.density.n_high * _COST_PER_TRIAL.get(t.planner_name, 1.0)


_R = TypeVar("_R")


class SizedTask(Protocol):
    """A unit of work that knows how many trials it runs (for the progress bar and the largest-first order)."""

    @property
    def n_trials(self) -> int: ...


_TaskT = TypeVar("_TaskT", bound=SizedTask)


def map_tasks(
    fn: Callable[[_TaskT], _R],
    tasks: Sequence[_TaskT],
    executor: Executor | None = None,
    *,
    workers: int | None = None,
    progress: ProgressFn | None = None,
    cost: Callable[[_TaskT], float] | None = None,
) -> list[_R]:
    """``[fn(t) for t in tasks]`` on ``executor`` (any ``concurrent.futures.Executor``: the process pool, Dask's
    ``Client.get_executor()``); ``fn`` must be a module-level function so process pools can pickle it.

    The tasks are submitted in decreasing ``cost`` (default: their trials), so the last ones to start are the
    cheapest and the workers finish close together. Results come back in task order, whatever order the workers
    finish in.
    """
    own = executor is None
    ex = default_executor(workers) if executor is None else executor
    total = sum(t.n_trials for t in tasks)
    done = 0
    results: dict[int, _R] = {}
    try:
        # Largest first keeps both workers busy until the end.
        key = cost if cost is not None else (lambda t: float(t.n_trials))
        order = sorted(range(len(tasks)), key=lambda i: -key(tasks[i]))
        with _single_thread_blas_env():
            futures = {ex.submit(fn, tasks[i]): i for i in order}
        pending = set(futures)
        if progress is not None:
            progress(0, total)
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                i = futures[fut]
                results[i] = fut.result()
                done += tasks[i].n_trials
            if progress is not None:
                progress(done, total)
    finally:
        if own:
            ex.shutdown(wait=True, cancel_futures=True)
    return [results[i] for i in range(len(tasks))]


def collect_cells(results: Sequence[ChunkResult]) -> list[CellResult]:
    """Group chunk results into (planner, density) cells, chunks in index order, cells in first-seen order."""
    groups: dict[tuple[str, Density], list[ChunkResult]] = {}
    for r in results:
        groups.setdefault((r.task.planner_name, r.task.density), []).append(r)
    cells = []
    for (name, density), parts in groups.items():
        parts.sort(key=lambda r: r.task.chunk_index)
        cells.append(
            CellResult(
                planner_name=name,
                density=density,
                records=TrialRecords.concat([p.records for p in parts]),
                wall_s=sum(p.wall_s for p in parts),
                cpu_s=sum(p.cpu_s for p in parts),
            )
        )
    return cells


def run_study(
    config: StudyConfig,
    planners: Sequence[str],
    densities: Sequence[Density],
    trials: int,
    seed: int,
    executor: Executor | None = None,
    *,
    workers: int | None = None,
    progress: ProgressFn | None = None,
) -> list[CellResult]:
    """The study: ``trials`` per (planner, density), as fixed seeded chunks on ``executor``.

    Returns one ``CellResult`` per (planner, density), planners outer, densities inner.
    """
    tasks = make_tasks(config, planners, densities, trials, seed)
    return collect_cells(run_tasks(tasks, executor, workers=workers, progress=progress))

"""What the `controller` node computes, without rclpy: history, answer rule, model, tick.

Index convention (the plant's, the NSSM's and the MPC's): a sample of step k carries y_k and
u_k, the input held over (k-1, k] that produced it. The tick answering step k plans
u_{k+1..k+N} from z_k = f_enc(u_{k-H+1..k}, y_{k-H+1..k}) (eq. (z)), the applied u_k and the
references at (k + 1..k + N) dt since the last reset (eq. (mpc)). Pieces, each testable
alone: :class:`History` (the last H samples), :class:`AnswerRule` (which tick answers which
sample), :class:`PreModelInput` (the input before a model), :func:`build_model` (weights ->
predictor + latent MPC, outside the tick; a feature NARX's: its regressor state s_t in place
of z_t, planned on its linearisation at each tick, :mod:`local_mpc`), :class:`Tuning` (what
a live change replaces), :class:`ControllerCore` (samples in; tick -> :class:`TickResult`
through the configured :class:`~metampc_controller.planner.Planner`).
"""
from dataclasses import dataclass, field, replace
import math
import threading
from typing import Any, List, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

from metampc_controller.adaptation_trigger import AdaptationTrigger, Request
from metampc_controller.controller_params import ControllerConfig, MAX_HISTORY
from metampc_common.excitation import excitation, ExcitationConfig
from metampc_controller.local_mpc import LocalLinearMpc
from metampc_controller.model_gate import ModelEvent, ModelGate
from metampc_controller.narx_rls import NarxRls, RlsCounts
from metampc_controller.mpc import LatentMpc, MpcConfig, NO_TIME_LIMIT
from metampc_controller.offset_free import disturbance_model
from metampc_controller.planner import Planner, PlanResult
from metampc_controller.planner_registry import learned_mpc, planner_kind, TrueModel
from metampc_controller.prediction_error import PredictionError
from metampc_model.latent_model import LatentModel
from metampc_model.narx_predictor import NarxPredictor
from metampc_model.predictor import NssmPredictor
from metampc_controller.references import make_reference
from metampc_model.weights_codec import DecodedNarx, DecodedWeights, WeightsError
from metampc_plant.plant_description import PlantDescription
from metampc_plant.registry import get_family


class History:
    """The last pairs (u_k, y_k) of the current episode, read as the encoder's H rows.

    A new episode starts when the step index does not follow the previous one (it went back:
    the plant was reset; or it jumped: samples were missed, or the controller started
    mid-run). Until an episode has H samples, the rows before its first sample repeat that
    sample. That is exact when the episode starts at rest at an equilibrium held since long,
    as the experiments do (x0 = [0, 0] with u = 0 is one for the van der Pol plant), and an
    approximation otherwise.

    Storage: each sample is written twice, at i and i + capacity of a 2 x capacity buffer, so
    the newest H rows are always one contiguous slice (no copy per tick).
    """

    def __init__(self, capacity: int, n_u: int, n_y: int):
        self.capacity = capacity
        self._lock = threading.Lock()     # append (executor) against snapshot (builder)
        self._u = np.zeros((2 * capacity, n_u))
        self._y = np.zeros((2 * capacity, n_y))
        self._pos = 0
        self.step: Optional[int] = None   # step index of the newest sample
        self.length = 0                   # samples in the current episode

    def append(self, step: int, u: Sequence[float], y: Sequence[float]) -> bool:
        """Add sample (u_k, y_k) of step k; True if it starts a new episode."""
        new_episode = self.step is None or step != self.step + 1
        with self._lock:
            if new_episode:
                self._u[:] = u
                self._y[:] = y
                self._pos, self.length = 0, 1
            else:
                pos = self._pos = (self._pos + 1) % self.capacity
                self.length += 1
                # Rows pos and pos + capacity in one assignment (one conversion of the value).
                self._u[pos::self.capacity] = u
                self._y[pos::self.capacity] = y
            self.step = step
        return new_episode

    def snapshot(self) -> Tuple[np.ndarray, np.ndarray]:
        """Copies (u (n, n_u), y (n, n_y)) of the current episode's samples held, oldest first
        (n = min(length, capacity)); safe from another thread."""
        with self._lock:
            if self.step is None:
                return np.zeros((0, self._u.shape[1])), np.zeros((0, self._y.shape[1]))
            n = min(self.length, self.capacity)
            end = self._pos + self.capacity + 1
            return self._u[end - n:end].copy(), self._y[end - n:end].copy()

    def window(self, h: int) -> Tuple[np.ndarray, np.ndarray]:
        """(u (h, n_u), y (h, n_y)): the newest h samples, oldest first (read-only views)."""
        if not 1 <= h <= self.capacity or self.step is None:
            raise ValueError(f'window of {h} samples from a history of capacity '
                             f'{self.capacity} with {self.length} samples')
        end = self._pos + self.capacity + 1
        return self._u[end - h:end], self._y[end - h:end]

    @property
    def u(self) -> np.ndarray:
        """Newest applied input u_k (n_u,)."""
        return self._u[self._pos]

    @property
    def y(self) -> np.ndarray:
        """Newest output y_k (n_y,)."""
        return self._y[self._pos]


class AnswerRule:
    """Which tick answers which plant sample, so that a lockstep run is deterministic.

    Each sample is answered at most once: a timer tick answers the newest unanswered sample;
    if there is none, the tick is pending and runs when the next sample arrives. The node
    starts with a pending tick, so the first sample (y_0 at sim time 0, before the sim-time
    timer's first period) is answered on arrival. Inactive: nothing is answered; activation
    answers the newest unanswered sample at once, or the next one on arrival.

    An activation may be bounded (:meth:`set_active`'s ``until_step``, ``stop_at_escape``).

    Under a lockstep plant (``lockstep`` True) every sample is answered on arrival: the plant
    sends y_k only once it has u_{k-1} and waits for u_k, so the tick of time k dt has
    nothing else to wait for, and waiting for /clock and the timer's callback as well would
    put two more callbacks of the node on the loop's critical path (measured: a third of
    the lockstep step time, docs/controller.md). The answers are the same either way.
    """

    def __init__(self, active: bool = True, lockstep: bool = False):
        self.active = active
        self.lockstep = lockstep
        self._unanswered = False
        self._pending = active
        self._until_step, self._stop_at_escape = 0, False     # the bounds of an activation

    def on_sample(self) -> bool:
        """A sample arrived; True if it is to be answered now (a tick was pending, or the
        plant is lockstep)."""
        self._unanswered = True
        if self.active and (self._pending or self.lockstep):
            self._pending = False
            return True
        return False

    def on_tick(self) -> bool:
        """The timer fired; True if the newest sample is to be answered now."""
        if not self.active:
            return False
        if self._unanswered:
            return True
        self._pending = True
        return False

    def answered(self, step: int) -> bool:
        """Sample `step` has been answered; True if that ends a bounded activation (its
        ``until_step``): inactive from now on."""
        self._unanswered = False
        if 0 < self._until_step <= step:
            self.set_active(False)
            return True
        return False

    def diverged(self) -> bool:
        """The newest sample is diverged; True if that ends an activation bounded by
        ``stop_at_escape`` (the sample stays unanswered): inactive from now on."""
        if self._stop_at_escape and self.active:
            self.set_active(False)
            return True
        return False

    @property
    def unanswered(self) -> bool:
        """The newest sample has not been answered (e.g. its answer waits for a model)."""
        return self._unanswered

    def set_active(self, active: bool, until_step: int = 0, stop_at_escape: bool = False
                   ) -> bool:
        """Switch; True if activation answers the newest sample now. An activation may be
        bounded: inactive by itself after answering `until_step` (> 0), or at the first
        diverged sample with `stop_at_escape`, so that a lockstep run stops exactly there
        however late its caller looks."""
        self._until_step, self._stop_at_escape = (until_step, stop_at_escape) if active else (
            0, False)
        was_active, self.active = self.active, active
        if not active:
            self._pending = False
            return False
        if was_active:
            return False
        if self._unanswered:
            return True
        self._pending = True
        return False


class PreModelInput:
    """The input before any model: 0 clipped into the bounds, or a seeded excitation.

    The excitation value answering step k is sample k of a signal that restarts with every
    plant reset (like the reference). It is generated in blocks of about BLOCK samples,
    whole hold periods each, block b from the seed sequence (seed, b): any step is reproducible
    without generating the ones before it.
    """

    BLOCK = 1000

    def __init__(self, kind: str, config: ExcitationConfig, seed: int, u_min: np.ndarray,
                 u_max: np.ndarray):
        self.kind = kind
        self.config = config
        self.seed = seed
        self._zero = np.clip(0.0, u_min, u_max)
        self._key: Optional[Tuple[int, float]] = None
        self._block = np.zeros((0, len(u_min)))

    def value(self, step: int, dt: float) -> np.ndarray:
        """The input (n_u,) answering step `step` at sample time dt (s)."""
        if self.kind == 'zero':
            return self._zero
        hold = max(1, int(round(self.config.hold_s / dt)))
        length = hold * -(-self.BLOCK // hold)
        block, index = divmod(step, length)
        if self._key != (block, dt):
            seed = int(np.random.SeedSequence([self.seed, block]).generate_state(1)[0])
            self._block = excitation(self.config, 1, length, dt, seed)[0]
            self._key = (block, dt)
        return self._block[index].copy()


@dataclass
class ModelBundle:
    """A model ready for the tick: its predictor (the NSSM's, or a feature NARX's), the MPC
    built on it (the latent MPC; a feature NARX's relinearised each tick), and the monitor of
    its prediction errors (None: the ticks neither measure them nor ask for adaptation; online
    collection, which reads neither, saves ~5 % of its time; a feature NARX has none)."""

    version: int
    method: str
    stage: str
    predictor: Union[NssmPredictor, NarxPredictor]
    mpc: Union[LatentMpc, LocalLinearMpc]
    prediction: Optional[PredictionError]

    @property
    def history(self) -> int:
        return self.predictor.history

    @property
    def latent(self) -> Optional[LatentModel]:
        """The NSSM's latent model (fixed), or None for a feature NARX, whose linearisation
        changes every tick: the model check, the prediction-error monitor (and the triggered
        rule's requests) and offset-free tracking are the NSSM's."""
        return getattr(self.predictor, 'latent', None)

    @property
    def failed_linearisations(self) -> int:
        """Ticks of this model whose linearisation failed (a feature NARX's; 0 otherwise)."""
        return getattr(self.mpc, 'failed_linearisations', 0)

    def describe(self) -> str:
        """One line: the model's sizes and how it is planned on (the node's log)."""
        p = self.predictor
        if self.latent is None:
            sh = p.shape
            return (f'feature NARX p={sh.order}, F={sh.features}, features {list(sh.hidden)}; '
                    'planned on its linearisation at each tick (offset-free none; no model '
                    'check or prediction-error monitor: the NSSM\'s; adaptation requests '
                    'periodic, or posterior under the in-loop RLS)')
        cfg, term = p.config, self.mpc.terminal
        return (f'H={cfg.history}, n_z={cfg.n_z}, encoder {list(cfg.hidden)}'
                + (f'; terminal cost fallback: {term.reason}' if term.dare_unusable else '')
                + f'; offset-free {self.mpc.describe_offset_free()}')

    @classmethod
    def of(cls, predictor: Union[NssmPredictor, NarxPredictor], version: int, method: str,
           stage: str, mpc_config: MpcConfig, monitor: bool = True) -> 'ModelBundle':
        """The bundle of a predictor: its MPC (the NSSM's: OSQP set-up and DARE, outside the
        tick) and, with `monitor` and an NSSM, its prediction-error monitor. ValueError if the
        MPC rejects the model."""
        latent = getattr(predictor, 'latent', None)
        prediction = PredictionError(latent, predictor.norm.y_std,
                                     predictor.config.loss_horizon) if (
            monitor and latent is not None) else None
        return cls(version, method, stage, predictor, learned_mpc(mpc_config, predictor),
                   prediction)


def build_model(decoded: Union[DecodedWeights, DecodedNarx], version: int, method: str,
                stage: str, mpc_config: MpcConfig, n_u: int, n_y: int, history: int = 0
                ) -> ModelBundle:
    """Check a decoded model (an NSSM or a feature NARX) against the plant and the controller,
    then build predictor + planner.

    Runs outside the tick (it sets up OSQP and solves the DARE). history: the H (a feature
    NARX: its order p) the weights must have (0: any up to MAX_HISTORY).

    Raises:
        WeightsError: one-line reason (dimensions, history, or a model the MPC rejects).
    """
    narx = isinstance(decoded, DecodedNarx)
    cfg = decoded.shape if narx else decoded.config
    if (cfg.n_u, cfg.n_y) != (n_u, n_y):
        raise WeightsError(f'model has n_u = {cfg.n_u}, n_y = {cfg.n_y}; the plant has '
                           f'{n_u} input(s), {n_y} output(s)')
    predictor = (NarxPredictor if narx else NssmPredictor)(cfg, decoded.norm, decoded.params)
    if predictor.history > MAX_HISTORY or (history and predictor.history != history):
        need = history or f'<= {MAX_HISTORY}'
        raise WeightsError(f'history H = {predictor.history}, the controller needs {need}')
    try:
        return ModelBundle.of(predictor, version, method, stage, mpc_config)
    except ValueError as err:
        raise WeightsError(str(err)) from None


@dataclass(frozen=True, eq=False)
class Tuning:
    """The settings that a live parameter change replaces, used by the ticks as one.

    Attributes:
        version: 0 as started, +1 per accepted change (``MpcStatus.config_version``).
        config: the controller's config (its ``mpc``: horizon, q, r, bounds).
        u_min, u_max: (n_u,) input bounds.
        q: output weights, as MpcStatus.q carries them.
        reference: the configured reference (references.make_reference).
        pre_model: the input before a model (its excitation lies within the bounds).
    """

    version: int
    config: ControllerConfig
    u_min: np.ndarray
    u_max: np.ndarray
    q: List[float]
    reference: Any
    pre_model: 'PreModelInput'

    @classmethod
    def of(cls, config: ControllerConfig, version: int, n_u: int) -> 'Tuning':
        """The tuning of a parsed config for a controller of n_u inputs."""
        u_min, u_max = config.mpc.bounds(n_u)
        return cls(version, config, u_min, u_max, [float(w) for w in config.mpc.q],
                   make_reference(config.reference_kind, **config.reference_params),
                   PreModelInput(config.pre_model_input, config.excitation,
                                 config.excitation_seed, u_min, u_max))


def bounds_exceeding(u_min: np.ndarray, u_max: np.ndarray, plant: 'PlantDescription') -> str:
    """'' if [u_min, u_max] lies within the plant's bounds, else a line that says it does
    not (the start-up warning, and the reason a live change is refused)."""
    if np.any(u_min < plant.u_min) or np.any(u_max > plant.u_max):
        return (f'input bounds [{u_min.tolist()}, {u_max.tolist()}] exceed the plant\'s '
                f'[{list(plant.u_min)}, {list(plant.u_max)}]')
    return ''


def tuning_refusal(config: ControllerConfig, n_u: int, n_y: int,
                   plant: Optional[PlantDescription], model: Optional[ModelBundle]) -> str:
    """What a running controller of n_u inputs and n_y outputs, on `plant` (None: not told)
    with `model` in use, refuses of a parsed config, beyond its parse: '' or the reason
    (other numbers of inputs or outputs; bounds beyond the plant's; an offset-free form the
    model in use fails)."""
    if config.n_y != n_y:
        return f'q needs one weight per output ({n_y}), got {list(config.mpc.q)}'
    if config.n_u not in (1, n_u):
        return (f'r, u_min and u_max need one value per input ({n_u}) or one for all, '
                f'got {list(np.atleast_1d(config.mpc.r))}, {list(config.mpc.u_min)}, '
                f'{list(config.mpc.u_max)}')
    if plant is not None and len(plant.u_min) == n_u:
        exceeding = bounds_exceeding(*config.mpc.bounds(n_u), plant)
        if exceeding:
            return f'{exceeding} (plant_info): a change must stay within them'
    if model is not None and model.latent is not None and config.mpc.offset_free != 'none':
        try:
            disturbance_model(model.latent, config.mpc.offset_free)
        except ValueError as err:
            return f'{err}, for the model in use (version {model.version})'
    return ''


class TickReferences:
    """The references a tick reads: set-points overriding the reference (a node's
    ``reference`` topic), else a table by step (an in-process caller), else the tuning's."""

    def __init__(self, n_y: int):
        self.n_y = n_y
        self._override: Optional[np.ndarray] = None
        self._table: Optional[np.ndarray] = None

    def set_override(self, values: Sequence[float]) -> str:
        """Set-points per output overriding the reference ([] clears); returns an error or ''."""
        values = np.asarray(values, dtype=float)
        if values.size == 0:
            self._override = None
        elif values.shape != (self.n_y,) or not np.all(np.isfinite(values)):
            return f'expected {self.n_y} finite set-points (or none), got {values.tolist()}'
        else:
            self._override = values
        return ''

    def set_table(self, table: Optional[np.ndarray]) -> None:
        """References by step for an in-process caller (online collection): row j of `table`
        (K, n_y) is r_j of every episode from the plant's reset on, in place of the tuning's
        reference (an override still wins); the tick answering step t reads rows t + 1..t + N,
        so K > the last step answered + N. None: the tuning's reference again.

        Raises:
            ValueError: a table that is not (K, n_y) and finite.
        """
        if table is not None:
            table = np.array(table, dtype=float)
            if table.ndim != 2 or table.shape[1] != self.n_y or not np.all(np.isfinite(table)):
                raise ValueError(f'references need a finite (K, {self.n_y}) table, got shape '
                                 f'{table.shape}')
            table.flags.writeable = False     # ticks hand out views of it (y_ref)
        self._table = table

    def horizon(self, step: int, tuning: Tuning, dt: float) -> np.ndarray:
        """(N, n_y) references of the horizon of the tick answering `step` under `tuning`,
        at sample time dt (s)."""
        n = tuning.config.mpc.horizon
        override, table = self._override, self._table
        if override is not None:
            out = np.empty((n, self.n_y))
            out[:] = override
            return out
        if table is not None:
            rows = table[step + 1:step + 1 + n]
            if len(rows) < n:
                raise ValueError(f'the reference table has {len(table)} rows; step {step} '
                                 f'needs rows up to {step + n}')
            return rows
        return tuning.reference.evaluate(step * dt, dt, n)


@dataclass
class TickResult:
    """One answer: the input and what the MpcStatus message reports (units as there).

    u: (n_u,) u_{k+1}, finite and within the bounds. u_plan (N, n_u), y_pred (N, n_y):
    empty (0 rows) when nothing was planned. y_ref: (N, n_y) references of the horizon.
    prediction_errors: the model's one-step and T-step errors at y_k and the outputs' change
    over those T steps (:class:`~metampc_controller.prediction_error.PredictionError`; NaN
    when none).
    request: the adaptation request this tick made (:mod:`adaptation_trigger`), if any.
    disturbance: the latent MPC's offset-free disturbance estimate (empty otherwise);
    slack: its largest planned violation of the soft output bounds.
    residual: the solver's optimality residual (:class:`~planner.PlanResult`; NaN: none).
    failed_linearisations: the model in use's ticks whose linearisation failed (a feature
        NARX's planner; 0 otherwise).
    events: the model gate's decisions since the previous answer (:mod:`model_gate`).
    detector: the adaptation trigger's statistic and baseline after this tick (triggered: the
        CUSUM and the baseline error; posterior: the chi-square window's sum and threshold).
    one_step_std: (n_y,) with rls_forgetting on a feature NARX: the std its head's posterior
        gave y_k's one-step prediction (:mod:`narx_rls`; NaN: none yet); empty otherwise.
    rls_event: what :mod:`narx_rls` did this tick that the log says ('' nothing).
    rls_counts: its counts for the model in use so far (the object it updates), or None.
    config_version: the :class:`Tuning` the tick used; q: its output weights.
    """

    step: int
    u: np.ndarray
    model_version: int
    config_version: int
    q: List[float]
    planner: str
    solver_status: str
    model_status: str
    cost: float
    iterations: int
    solve_time: float
    fallback: bool
    terminal_fallback: bool
    u_plan: np.ndarray
    y_pred: np.ndarray
    y_ref: np.ndarray
    prediction_errors: Tuple[float, float, float]
    request: Optional[Request] = None
    disturbance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    slack: float = 0.0
    events: Tuple[ModelEvent, ...] = ()
    residual: float = math.nan
    failed_linearisations: int = 0
    detector: Tuple[float, float] = (0.0, math.nan)
    one_step_std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rls_event: str = ''
    rls_counts: Optional[RlsCounts] = None


# No model, no prediction: the (one-step, T-step, T-step change) of a tick without the model.
NO_ERRORS = (math.nan, math.nan, math.nan)
NO_SPREAD = np.zeros(0)     # no in-loop RLS: no one-step std


def nmpc_unavailable(reason: str) -> str:
    """The line that says the nmpc planner has no model of the plant, and why."""
    return (f'planner nmpc: the plant\'s model is not available ({reason}); answering with the '
            'pre-model input')


class TrueModelPlanner:
    """The planner on the plant's equations (a kind not learned: nmpc): built once per plant
    (family, dt), theta told first, or tuning; it takes a new theta by set_theta. Its
    ``problem``: why there is none ('' if there is one, or nothing to say yet)."""

    def __init__(self, kind):
        self.kind = kind
        self.planner: Optional[Planner] = None
        self.theta: Tuple[float, ...] = ()      # the newest sample's theta ((): untold)
        self.problem = ''

    def build(self, plant: Optional[PlantDescription], tuning: Tuning) -> str:
        """Build it with the samples' theta and the tuning (NMPC: no set-up, cheap) and swap
        it in as one reference; '' or why there is none. No sample has told theta yet: none,
        and nothing to say."""
        if plant is None or self.kind.learned:
            return ''
        try:
            family = get_family(plant.family)
            if not self.theta:
                self.planner = None
                return ''
            planner = self.kind.build(tuning.config, TrueModel(family, self.theta, plant.dt))
        except ValueError as err:     # unknown family, or a wrong theta
            self.planner = None
            return str(err)
        self.planner = planner
        return ''

    def tell(self, theta: Tuple[float, ...], plant: Optional[PlantDescription],
             tuning: Tuning) -> None:
        """A sample's theta (() : untold; ControllerCore.observe)."""
        if not theta:
            if not self.theta:
                self.problem = nmpc_unavailable('the plant\'s samples tell no theta')
            return
        if theta == self.theta:
            return
        self.theta = theta
        planner, error = self.planner, ''
        if planner is None:
            error = self.build(plant, tuning)
        else:
            try:
                planner.set_theta(theta)    # warm start kept, nothing rebuilt
            except ValueError as err:
                self.planner, error = None, str(err)
        self.problem = nmpc_unavailable(error) if error else ''


class _Setup(NamedTuple):
    """What a tick reads once: the tuning, the model built for it, and the model status."""

    tuning: Tuning
    model: Optional[ModelBundle]
    model_status: str

    def after(self, events: Sequence[ModelEvent]) -> '_Setup':
        """The set-up once the gate's `events` took effect (the model they fly, their
        status)."""
        setup = self
        for event in events:
            if event.model is not None:
                setup = setup._replace(model=event.model)
            if event.status is not None:
                setup = setup._replace(model_status=event.status)
        return setup


class ControllerCore:
    """The controller's state and tick, in physical units (module docstring).

    Threading: everything runs on the node's executor thread except :meth:`offer`,
    :meth:`refuse` and :meth:`retune`, which the node's builder thread calls, one at a
    time and in the order of their requests. They replace one (tuning, model, status) tuple
    that a tick reads once, so a new model or tuning is swapped in between two ticks and a
    tick never mixes two. When a new model flies is the gate's (:attr:`gate`).
    """

    def __init__(self, config: ControllerConfig):
        self.kind = planner_kind(config.planner)    # not live: looked up once
        self.n_u, self.n_y = config.n_u, config.n_y
        self.history = History(MAX_HISTORY, self.n_u, self.n_y)
        self.plant: Optional[PlantDescription] = None
        self._references = TickReferences(self.n_y)
        self._true = TrueModelPlanner(self.kind)    # nmpc; a learned kind's is its model's
        self._setup = _Setup(Tuning.of(config, 0, self.n_u), None, 'none')
        self._setup_lock = threading.Lock()     # the builder thread and a queued swap
        self._events: List[ModelEvent] = []     # the gate's, until a tick publishes them
        self.trigger = AdaptationTrigger(config.trigger)
        self.gate: ModelGate[ModelBundle] = ModelGate(self.trigger, self.history.snapshot)
        # A feature NARX's head adapted at every tick (rls_forgetting > 0; not live).
        self.rls = NarxRls(config.rls) if config.rls.rls_forgetting > 0 else None

    # --- inputs from other callbacks ----------------------------------------------------

    @property
    def tuning(self) -> Tuning:
        """The tuning of the next tick (the latest retune())."""
        return self._setup.tuning

    @property
    def config(self) -> ControllerConfig:
        return self._setup.tuning.config

    @property
    def u_min(self) -> np.ndarray:
        return self._setup.tuning.u_min

    @property
    def u_max(self) -> np.ndarray:
        return self._setup.tuning.u_max

    @property
    def model(self) -> Optional[ModelBundle]:
        return self._setup.model

    @property
    def model_status(self) -> str:
        return self._setup.model_status

    def offer(self, bundle: ModelBundle, request_step: int = 0) -> ModelEvent:
        """A new model (built for :attr:`tuning`; builder thread), naming the adaptation
        request of `request_step` (0: none), to the gate: the event it decided at arrival
        (flew: in use from the next tick; queued; refused)."""
        with self._setup_lock:      # not between set_plant's clock rule and the offer
            bundle.mpc.set_time_limit(self._time_limit())
        event = self.gate.offer(bundle, request_step, self.model, self.config)
        self._take([event])
        return event

    def refuse(self, version: int, request_step: int, reason: str) -> ModelEvent:
        """Weights that could not be built (`reason`: why; builder thread): the model in use
        stays, the event says why."""
        event = self.gate.refuse(version, request_step, reason)
        self._take([event])
        return event

    def _take(self, events: List[ModelEvent]) -> None:
        """Apply the gate's `events` to the set-up and keep them for the next tick's answer."""
        with self._setup_lock:
            self._setup = self._setup.after(events)
            self._events.extend(events)

    def _time_limit(self, config: Optional[ControllerConfig] = None) -> float:
        """OSQP's wall-clock cap per solve for the planners (of `config`, default the
        tuning's): none under a lockstep plant, which waits for every answer (a cap that
        trips on a stalled machine only turns a seeded run into another), else
        ``time_limit``. Set in place (warm starts kept), so a plan never depends on when
        plant_info came."""
        plant = self.plant
        if plant is not None and plant.lockstep:
            return NO_TIME_LIMIT
        return (config or self.config).mpc.time_limit

    def waits_for_model(self) -> bool:
        """True if the newest sample's answer must wait for the requested model (lockstep:
        its swap step has come and the model is not there yet)."""
        return self.gate.waits(self.history.step)

    def check_tuning(self, config: ControllerConfig) -> str:
        """What the running controller refuses of a parsed config: :func:`tuning_refusal`."""
        return tuning_refusal(config, self.n_u, self.n_y, self.plant, self.model)

    def retune(self, config: ControllerConfig, version: int) -> None:
        """Use `config` as tuning `version` from the next tick on (builder thread).

        Builds the planner of the model in use for it (the QP's OSQP set-up and DARE:
        milliseconds, while the ticks go on with the tuning before), then swaps it in; the
        new planner starts cold, as on a new model. ValueError if the model does not fit
        (check_tuning first)."""
        def rebuilt(bundle: ModelBundle) -> ModelBundle:
            mpc = learned_mpc(config.mpc, bundle.predictor)
            mpc.set_time_limit(limit)
            return replace(bundle, mpc=mpc)

        with self._setup_lock:
            setup = self._setup
            limit = self._time_limit(config)
            model = setup.model
            if model is not None:
                model = rebuilt(model)
            tuning = Tuning.of(config, version, self.n_u)
            if self._true.planner is not None:
                self._true.build(self.plant, tuning)    # here, never in the tick
            self.gate.retune(rebuilt)
            self._setup = setup._replace(tuning=tuning, model=model)
        self.trigger.config = config.trigger

    @property
    def nmpc_problem(self) -> str:
        """Why the nmpc planner has no model of the plant, or ''."""
        return self._true.problem

    @property
    def dt(self) -> float:
        """Sample time, s: the plant's, or 1 / rate_hz until plant_info has arrived."""
        return self.plant.dt if self.plant is not None else 1.0 / self.config.rate_hz

    def set_plant(self, plant: PlantDescription) -> List[str]:
        """Take the plant's description; returns warnings about disagreeing settings."""
        self.gate.lockstep = plant.lockstep
        tuning = self.tuning
        cfg = tuning.config
        warnings = []
        if (len(plant.u_min), plant.n_y) != (self.n_u, self.n_y):
            warnings.append(f'the plant ({plant.family or "unnamed"}) has {len(plant.u_min)} '
                            f'input(s) and {plant.n_y} output(s), this controller {self.n_u} '
                            f'and {self.n_y} (u_min / u_max / r and q): its inputs will be '
                            'rejected')
            self.plant = plant
            return warnings
        exceeding = bounds_exceeding(tuning.u_min, tuning.u_max, plant)
        if exceeding:
            warnings.append(f'{exceeding}: the plant will saturate what the MPC plans')
        if plant.lockstep and cfg.rate_hz * plant.dt < 1.0 - 1e-9:
            warnings.append(f'rate_hz {cfg.rate_hz} is below the lockstep plant\'s 1/dt = '
                            f'{1.0 / plant.dt}: steps will wait for input timeouts')
        known = self.plant
        self.plant = plant
        if known is None or known.lockstep != plant.lockstep:
            self._apply_time_limit()
        if known is None or (known.family, known.dt) != (plant.family, plant.dt):
            error = self._true.build(plant, tuning)
            if error:
                warnings.append(nmpc_unavailable(error))
        return warnings

    def _apply_time_limit(self) -> None:
        """The clock rule (:meth:`_time_limit`) on the model in use and a queued or tried
        answer, in place (executor thread, between ticks)."""
        def limited(bundle: ModelBundle) -> ModelBundle:
            bundle.mpc.set_time_limit(limit)
            return bundle

        with self._setup_lock:
            limit = self._time_limit()
            if self.model is not None:
                limited(self.model)
            self.gate.retune(limited)

    def set_override(self, values: Sequence[float]) -> str:
        """:meth:`TickReferences.set_override`."""
        return self._references.set_override(values)

    def set_references(self, table: Optional[np.ndarray]) -> None:
        """:meth:`TickReferences.set_table`."""
        self._references.set_table(table)

    def observe(self, step: int, u: Sequence[float], y: Sequence[float],
                theta: Sequence[float] = ()) -> bool:
        """Record plant sample k (and theta(k dt) where the plant tells it); True if it starts
        a new episode.

        The samples are the one channel of theta (planner nmpc; empty: the sample does not
        tell it, the last told stays): the NMPC yardstick predicts with the theta of the
        sample it plans from, under a theta_schedule too, ramps included; plant_info (family,
        dt) is re-sent at a schedule's segments only, on its own time, and a lockstep run must
        not depend on when. A theta that does not fit the family leaves no NMPC
        (:attr:`nmpc_problem` says why; the ticks answer with the pre-model input).

        A new episode (a plant reset, or a gap in the steps) starts the planners cold, as
        on a fresh model: what the previous episode left (warm start, OSQP's duals and rho)
        never reaches it, so a lockstep episode replays exactly whatever the controller
        answered before it (e.g. a stale sample at activation)."""
        new_episode = self.history.append(step, u, y)
        if new_episode:
            model = self.model
            for planner in (self._true.planner, model.mpc if model is not None else None):
                if planner is not None:
                    planner.reset()
            self.trigger.new_episode()
            self.gate.new_episode()
        if not self.kind.learned:
            self._true.tell(tuple(theta), self.plant, self.tuning)
        return new_episode

    # --- the tick -----------------------------------------------------------------------

    def references(self, step: int, tuning: Optional[Tuning] = None) -> np.ndarray:
        """(N, n_y) references of the horizon of the tick answering `step` (with `tuning`,
        default the next tick's)."""
        return self._references.horizon(step, self.tuning if tuning is None else tuning,
                                        self.dt)

    def tick(self) -> TickResult:
        """Answer the newest sample (observe() must have been called at least once)."""
        history = self.history
        step = history.step
        with self._setup_lock:  # not between a retune's rebuild of the answer and its swap
            decided = self.gate.tick(step, self.model, self.config)
            self._setup = self._setup.after(decided)
            events, self._events = tuple(self._events + decided), []
        tuning, model, model_status = self._setup
        u_prev = history.u
        y_ref = self.references(step, tuning)
        errors, request, version, state, failed = NO_ERRORS, None, 0, None, 0
        spread = NO_SPREAD
        if self.kind.learned:
            planner = None
            if model is not None:
                u_hist, y_hist = history.window(model.history)
                state = model.predictor.encode(u_hist, y_hist)
                innovation = None
                if self.rls is not None and model.latent is None:
                    spread = self.rls.tick(model.predictor, step, state, u_prev, history.y,
                                           tuning.u_min, tuning.u_max)
                    innovation = self.rls.innovation
                if model.prediction is not None:
                    errors = model.prediction.update(step, u_prev, history.y, state)
                if model.prediction is not None or model.latent is None:
                    request = self.trigger.update(step, self.dt, errors[1], errors[2],
                                                  model.version, innovation)
                planner, version = model.mpc, model.version
        else:
            planner = self._true.planner
        if planner is not None:
            res = planner.solve(state, u_prev, y_ref, history.y, step)
            if model is not None:
                failed = model.failed_linearisations
        else:
            res = PlanResult(u=tuning.pre_model.value(step, self.dt), u_plan=np.zeros(
                (0, self.n_u)), y_pred=np.zeros((0, self.n_y)), cost=math.nan,
                status=self.kind.waiting, iterations=-1, solve_time=0.0)
        result = tick_result(step, tuning, model_status, y_ref, u_prev, res, version, errors,
                             request, events, failed, (self.trigger.statistic,
                                                       self.trigger.baseline))
        if self.rls is not None:
            result.one_step_std, result.rls_event = spread, self.rls.event
            result.rls_counts = self.rls.counts
        return result


def tick_result(step: int, tuning: Tuning, model_status: str, y_ref: np.ndarray,
                u_prev: np.ndarray, res: PlanResult, version: int, errors: tuple,
                request: Optional[Request], events: Tuple[ModelEvent, ...] = (),
                failed: int = 0, detector: Tuple[float, float] = (0.0, math.nan)
                ) -> TickResult:
    """The tick's result from any planner's plan, with u checked: finite (else u_prev, or
    0, and `fallback`) and clipped into the tuning's bounds (the planners promise both;
    the plant must get it)."""
    u, fallback = np.asarray(res.u, dtype=float), res.fallback
    if not all(map(math.isfinite, u.tolist())):
        u = np.where(np.isfinite(u_prev), u_prev, 0.0)
        fallback = True
    u = np.maximum(u, tuning.u_min)     # np.clip's result, without its overhead
    np.minimum(u, tuning.u_max, out=u)
    return TickResult(step=step, u=u, planner=tuning.config.planner,
                      model_status=model_status, y_ref=y_ref,
                      config_version=tuning.version, q=tuning.q, fallback=fallback,
                      model_version=version, terminal_fallback=res.terminal_fallback,
                      solver_status=res.status, cost=float(res.cost),
                      iterations=int(res.iterations), solve_time=res.solve_time,
                      u_plan=res.u_plan, y_pred=res.y_pred, prediction_errors=errors,
                      request=request, disturbance=res.disturbance, slack=res.slack,
                      events=events, residual=res.residual, failed_linearisations=failed,
                      detector=detector)

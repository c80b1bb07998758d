"""When a new model may fly in the controller: offer, trial, probation, refusal and revert.

Any offered model flies from the next tick, checked at arrival where ``model_check`` says so,
except the answer to the pending adaptation request (``request_step`` r): queued for the tick
of step r + swap_delay under lockstep (that tick waits for it), for the next tick in real
time; with a trial of P samples it is tried from then (the model in use goes on) and judged P
samples later; flown with a probation of Q samples it is judged again Q samples later on its
own loop against the model it replaced, which comes back if it fails (a feature NARX's answer:
neither, the check is the NSSM's). The request is pending until the last verdict; a refusal
ends it. Each decision is a :class:`ModelEvent`, applied and published as it is
(MpcStatus.model_events). Pure Python: :meth:`ModelGate.offer` and :meth:`~ModelGate.retune`
run on the builder thread, the rest on the executor thread. Why: docs/controller.md.
"""
from dataclasses import dataclass
from enum import Enum
import threading
from typing import (Callable, Generic, List, NamedTuple, Optional, Protocol, Tuple, TypeVar)

import numpy as np

from metampc_common.params import param
from metampc_controller.adaptation_trigger import AdaptationTrigger, Request
from metampc_controller.model_check import check, ModelCheckConfig, Verdict
from metampc_controller.mpc import MpcConfig

CHECKED = ('requested', 'all', 'off')


@dataclass
class GateConfig:
    """When a new model may fly (node parameters, live); how it is scored: ModelCheckConfig."""

    model_check: str = param('requested', 'which new models must pass the check before they '
                                          'fly: requested (answers to adaptation requests, '
                                          'late ones too), all, off', choices=CHECKED,
                             live=True)
    model_check_trial: int = param(50, 'samples an answer to an adaptation request is tried on '
                                       'before it flies, the model in use going on meanwhile '
                                       '(scored on them alone: its adaptation never saw them); '
                                       '0: checked at arrival like any model; else at least '
                                       'the horizon', ge=0, le=900, live=True)
    model_check_probation: int = param(0, 'samples a requested model that flew is judged on, '
                                          'on its own loop, against the model it replaced, '
                                          'which comes back if it predicts them better; 0: '
                                          'none; else at least the horizon', ge=0, le=900,
                                       live=True)

    def checks(self, requested: bool) -> bool:
        """Whether a new model is checked: `requested` if it names an adaptation request."""
        return self.model_check == 'all' or (self.model_check == 'requested' and requested)


class Settings(Protocol):
    """What the gate reads of the controller's tuning (a ControllerConfig is one)."""

    mpc: MpcConfig
    model_check: ModelCheckConfig
    gate: GateConfig


class Candidate(Protocol):
    """What the gate reads of a model (the controller's ModelBundle is one)."""

    version: int
    method: str
    predictor: object
    latent: object
    mpc: object


Model = TypeVar('Model', bound=Candidate)


class Outcome(Enum):
    """What the gate decided about a model (MpcStatus.model_events[].outcome)."""

    QUEUED = 'queued'           # the answer to the pending request waits for its step (start)
    FLEW = 'flew'               # in use from this tick
    ON_TRIAL = 'on_trial'       # tried from this tick; the model in use goes on
    REFUSED = 'refused'         # never used; the model in use stays
    REVERTED = 'reverted'       # its probation failed: the model it replaced is back
    KEPT = 'kept'               # its probation passed: the request is answered


class Cause(Enum):
    """What decided it (MpcStatus.model_events[].cause)."""

    WEIGHTS = 'weights'         # the weights could not be built into a model
    CHECK = 'check'             # the check (its numbers in the event's verdict)
    UNCHECKED = 'unchecked'     # no check (none applies, too few samples, or not yet)


@dataclass(frozen=True)
class ModelEvent(Generic[Model]):
    """One decision of the gate about model `version`.

    Attributes:
        outcome: see :class:`Outcome`. request_step: the request it answers (0: none).
        verdict: the check's, when one decided or was made (None: no check).
        where, yardstick: the samples it scored and the model it was compared with (words).
        weights: REFUSED before any check: why the weights could not be built.
        model: the model in use from this event on (FLEW: it; REVERTED: the one it
            replaced); None: the model in use stays.
        start: QUEUED: the step whose tick uses or tries it (0: the next tick).
        trial: QUEUED, ON_TRIAL: the samples it is tried on (0: none).
        at_arrival: decided when the model arrived (builder thread), else at a tick.
    """

    outcome: Outcome
    version: int
    request_step: int = 0
    verdict: Optional[Verdict] = None
    where: str = 'the latest of the episode'
    yardstick: str = 'the model in use'
    weights: str = ''
    model: Optional[Model] = None
    start: int = 0
    trial: int = 0
    at_arrival: bool = False

    @property
    def cause(self) -> Cause:
        if self.weights:
            return Cause.WEIGHTS
        verdict = self.verdict
        return Cause.CHECK if verdict is not None and (verdict.scored or verdict.error) \
            else Cause.UNCHECKED

    @property
    def reason(self) -> str:
        """One line: the weights' fault, or the check's verdict ('' without either)."""
        if self.weights or self.verdict is None:
            return self.weights
        return self.verdict.reason(self.where, self.yardstick)

    @property
    def status(self) -> Optional[str]:
        """MpcStatus.model_status from this event on ('ok', 'rejected: <reason>',
        'reverted: <reason>'); None: as it was."""
        if self.outcome is Outcome.FLEW:
            return 'ok'
        if self.outcome in (Outcome.REFUSED, Outcome.REVERTED):
            word = 'rejected' if self.outcome is Outcome.REFUSED else 'reverted'
            return f'{word}: {self.reason}'
        return None


class _Answer(NamedTuple):
    """An answer the gate has: from `step` on (queued: its tick; tried or on probation:
    the first scored), the `trial` and `probation` samples it has, the request it answers,
    and (on probation) the model it replaced."""

    step: int
    model: object
    trial: int
    probation: int
    request: int
    replaced: object = None


class ModelGate(Generic[Model]):
    """The decisions of one controller about its models (module docstring).

    Args:
        trigger: the controller's request rule; its ``pending`` request is the one an answer
            must name, told when the answer is used for good (``answered``) or not
            (``give_up``).
        samples: () -> (u (K, n_u), y (K, n_y)), the episode's samples so far (the check's).
        lockstep: the plant is lockstep (the controller sets it from plant_info).
    """

    def __init__(self, trigger: AdaptationTrigger,
                 samples: Callable[[], Tuple[np.ndarray, np.ndarray]], lockstep: bool = False):
        self.trigger = trigger
        self.samples = samples
        self.lockstep = lockstep
        self._lock = threading.Lock()
        self._queued: Optional[_Answer] = None
        self._trial: Optional[_Answer] = None
        self._probation: Optional[_Answer] = None

    # --- offers (builder thread) ----------------------------------------------------------

    def offer(self, model: Model, request_step: int, in_use: Optional[Model],
              settings: Settings) -> ModelEvent:
        """A new model naming `request_step` (0: none), `in_use` flying: FLEW (from the next
        tick), QUEUED (the answer to the pending request) or REFUSED (by the check; an answer
        to the pending request so refused ends it)."""
        trial = self.tried(request_step, in_use, settings) if model.latent is not None else 0
        verdict = None
        if not trial and settings.gate.checks(bool(request_step)):
            verdict, event = self._arrival_check(model, request_step, in_use, settings)
            if event is not None:
                return event
        probation = self._probation_of(request_step, settings) if model.latent is not None else 0
        start = self._queue(model, request_step, trial, probation)
        if start is not None:
            return ModelEvent(Outcome.QUEUED, model.version, request_step, verdict,
                              start=start, trial=trial, at_arrival=True)
        if trial:   # its request ended since: a late answer, checked at arrival like one
            verdict, event = self._arrival_check(model, request_step, in_use, settings)
            if event is not None:
                return event
        return ModelEvent(Outcome.FLEW, model.version, request_step, verdict, model=model,
                          at_arrival=True)

    def _arrival_check(self, model: Model, request_step: int, in_use: Optional[Model],
                       settings: Settings) -> Tuple[Optional[Verdict], Optional[ModelEvent]]:
        """The check at arrival on the latest window: (its verdict, the REFUSED event or
        None). A feature NARX flies unchecked (the check is the NSSM's)."""
        if model.latent is None:
            return None, None
        verdict = self._check(model, in_use, settings)
        if verdict.ok:
            return verdict, None
        if self.answers(request_step):
            self.trigger.give_up()
        return verdict, ModelEvent(Outcome.REFUSED, model.version, request_step, verdict,
                                   at_arrival=True)

    def refuse(self, version: int, request_step: int, weights: str) -> ModelEvent:
        """Weights that could not be built into a model (`weights`: why): REFUSED."""
        return ModelEvent(Outcome.REFUSED, version, request_step, weights=weights,
                          at_arrival=True)

    def tried(self, request_step: int, in_use: Optional[Model], settings: Settings) -> int:
        """Samples the answer naming `request_step` is tried on before it flies (0: none): the
        trial for the answer to the pending request when it is checked and a model is in use
        to go on meanwhile."""
        gate = settings.gate
        if (not gate.checks(bool(request_step)) or in_use is None
                or not self.answers(request_step)):
            return 0
        return gate.model_check_trial

    def _probation_of(self, request_step: int, settings: Settings) -> int:
        """Samples the answer naming `request_step` is on probation for once it flies (0:
        none)."""
        gate = settings.gate
        if not (gate.checks(bool(request_step)) and self.answers(request_step)):
            return 0
        return gate.model_check_probation

    def _queue(self, model: Model, request_step: int, trial: int, probation: int
               ) -> Optional[int]:
        """Queue the answer to the pending request until its step: that step (0: the next
        tick), or None for any other model."""
        pending = self.trigger.pending      # once: a reset may forget it meanwhile
        if not request_step or pending is None or request_step != pending.step:
            return None
        start = pending.swap_step if self.lockstep else 0
        with self._lock:
            self._queued = _Answer(start, model, trial, probation, request_step)
        return start

    def retune(self, rebuild: Callable[[Model], Model]) -> None:
        """A live change of the tuning: the queued or tried answer and the model a flown one
        replaced are rebuilt for it (`rebuild`), as the controller rebuilds the model in use."""
        for slot, name in (('_queued', 'model'), ('_trial', 'model'),
                           ('_probation', 'replaced')):
            with self._lock:
                answer = getattr(self, slot)
            if answer is None:
                continue
            model = rebuild(getattr(answer, name))
            with self._lock:
                if getattr(self, slot) is answer:     # not used or forgotten meanwhile
                    setattr(self, slot, answer._replace(**{name: model}))

    # --- requests -------------------------------------------------------------------------

    def answers(self, request_step: int) -> bool:
        """True if a model naming `request_step` (0: none) answers the pending request."""
        pending = self.trigger.pending
        return bool(request_step) and pending is not None and request_step == pending.step

    def has_answer(self) -> bool:
        """True while the answer to the pending request is queued, tried or on probation."""
        return (self._queued, self._trial, self._probation) != (None, None, None)

    def waits(self, step: int) -> bool:
        """True if the tick of `step` must wait for the requested model (lockstep: its swap
        step has come and the gate has no answer)."""
        return self.lockstep and not self.has_answer() and self.trigger.waits(step)

    def time_out(self, request: Request) -> bool:
        """`request` waited too long: given up (True) if still pending with no answer in hand."""
        if self.trigger.pending is not request or self.has_answer():
            return False
        self.trigger.give_up()
        return True

    def learner_refused(self, request_step: int) -> Optional[Request]:
        """The learner cannot answer the request of `request_step`: the pending request it
        ends (None: not the pending one)."""
        pending = self.trigger.pending
        if not self.answers(request_step):
            return None
        self.trigger.give_up()
        return pending

    def new_episode(self) -> None:
        """A plant reset: the queued, tried or probation answer is forgotten."""
        with self._lock:
            self._queued = self._trial = self._probation = None

    # --- ticks (executor thread) ----------------------------------------------------------

    def tick(self, step: int, in_use: Optional[Model], settings: Settings
             ) -> List[ModelEvent]:
        """The decisions that take effect at the tick of `step`, `in_use` flying before: the
        queued answer's (FLEW or ON_TRIAL), then the verdict of a trial or a probation that
        this tick ends."""
        events = []
        due = self._due(step, in_use)
        if due is not None:
            events.append(due)
            in_use = due.model or in_use
        end = self._end_trial(step, in_use, settings) or self._end_probation(step, settings)
        if end is not None:
            events.append(end)
        return events

    def _due(self, step: int, in_use: Optional[Model]) -> Optional[ModelEvent]:
        with self._lock:
            queued = self._queued
            if queued is None or step < queued.step:
                return None
            self._queued = None
            if queued.trial:
                self._trial = queued._replace(step=step)
                return ModelEvent(Outcome.ON_TRIAL, queued.model.version, queued.request,
                                  trial=queued.trial)
        self._fly(step, queued._replace(step=step), in_use)
        return ModelEvent(Outcome.FLEW, queued.model.version, queued.request,
                          model=queued.model)

    def _fly(self, step: int, answer: _Answer, replaced: Optional[Model]) -> None:
        """`answer`'s model is used from the tick of `step`: on probation, or answered."""
        if answer.probation and replaced is not None:
            with self._lock:
                self._probation = answer._replace(step=step, replaced=replaced)
        else:
            self.trigger.answered(answer.model.version)

    def _end_trial(self, step: int, in_use: Optional[Model], settings: Settings
                   ) -> Optional[ModelEvent]:
        """The verdict on the answer whose trial the tick of `step` ends, on samples
        first..step against the model in use: FLEW (on probation if it has one) or REFUSED
        (the request ends)."""
        with self._lock:
            trial = self._trial
            if trial is None or step < trial.step + trial.trial:
                return None
            self._trial = None
        model = trial.model
        verdict = self._check(model, in_use, settings, scored=step - trial.step + 1)
        where = f'its trial from step {trial.step}, unseen by its adaptation'
        if not verdict.ok:
            self.trigger.give_up()
            return ModelEvent(Outcome.REFUSED, model.version, trial.request, verdict, where)
        self._fly(step, trial, in_use)
        return ModelEvent(Outcome.FLEW, model.version, trial.request, verdict, where,
                          model=model)

    def _end_probation(self, step: int, settings: Settings) -> Optional[ModelEvent]:
        """The verdict on the flown answer whose probation the tick of `step` ends, on the
        samples of its own loop against the model it replaced: KEPT (the request is
        answered) or REVERTED (that model comes back, cold; the request ends)."""
        with self._lock:
            answer = self._probation
            if answer is None or step < answer.step + answer.probation:
                return None
            self._probation = None
        flown, replaced = answer.model, answer.replaced
        verdict = self._check(flown, replaced, settings, scored=step - answer.step + 1)
        where, yardstick = (f'its probation from step {answer.step}, on its own loop',
                            'the model it replaced')
        if verdict.ok:
            self.trigger.answered(flown.version)
            return ModelEvent(Outcome.KEPT, flown.version, answer.request, verdict, where,
                              yardstick)
        self.trigger.give_up()
        replaced.mpc.reset()        # cold, as on a new model: its plan and p are stale
        return ModelEvent(Outcome.REVERTED, flown.version, answer.request, verdict, where,
                          yardstick, model=replaced)

    def _check(self, model: Model, against: Optional[Model], settings: Settings,
               scored: Optional[int] = None) -> Verdict:
        """:func:`model_check.check` of `model` on the episode's samples (the latest window,
        or the last `scored`) against `against` when of its method, persistence otherwise."""
        u, y = self.samples()
        same = against is not None and against.method == model.method
        return check(model.predictor, against.predictor if same else None, u, y,
                     settings.mpc, settings.model_check, scored)


__all__ = ['CHECKED', 'GateConfig', 'Outcome', 'Cause', 'ModelEvent', 'ModelGate']

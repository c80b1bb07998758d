"""When a new model applies in the controller: the swap rules, without rclpy or threads.

Any model is used from the next tick, except the answer to the pending adaptation request
(``request_step`` r): lockstep, from the tick of step r + swap_delay exactly (queued; that tick
waits for it), real time, from the next tick. With a trial of P samples it is tried from then
(the model in use goes on) and judged P samples later (:meth:`ModelSwap.trial_over`); flown with
a probation of Q samples it is judged again Q samples later on its own loop against the model it
replaced, which comes back if it fails (:meth:`ModelSwap.probation_over`); the request is
pending until the last verdict. A refused model is never used; a refusal or a given-up request
ends the wait at once. A live change rebuilds the answer's and the replaced model's QP; a plant
reset forgets them. Threads: :meth:`offer`, :meth:`answers`, :meth:`refused`, :meth:`retune` on
the builder thread, the rest on the executor thread; the answer is handed over under a lock.
"""
import threading
from typing import Callable, Generic, Optional, Protocol, Tuple, TypeVar

from metampc_controller.adaptation_trigger import AdaptationTrigger


class Versioned(Protocol):
    version: int


Model = TypeVar('Model', bound=Versioned)


class ModelSwap(Generic[Model]):
    """The swap rules of one controller (module docstring).

    Args:
        trigger: the controller's request rule; its ``pending`` request is the one an answer
            must name, and it is told when the answer is used for good (``answered``) or
            refused (``give_up``).
        lockstep: the plant is lockstep (the core sets it from plant_info).
    """

    def __init__(self, trigger: AdaptationTrigger, lockstep: bool = False):
        self.trigger = trigger
        self.lockstep = lockstep
        self._lock = threading.Lock()
        # (from step, answer, trial samples, probation samples)
        self._queued: Optional[Tuple[int, Model, int, int]] = None
        self._trial: Optional[Tuple[int, Model, int, int]] = None
        # (from step, the flown answer, the model it replaced, probation samples)
        self._probation: Optional[Tuple[int, Model, Model, int]] = None
        self._after_trial = 0       # probation samples of the answer whose trial just ended

    def answers(self, request_step: int) -> bool:
        """True if a model naming `request_step` (0: none) answers the pending request."""
        pending = self.trigger.pending
        return bool(request_step) and pending is not None and request_step == pending.step

    def holds_answer(self) -> bool:
        """True while the answer to the pending request is queued, tried or on probation (the
        request is answered; only a verdict is still to come)."""
        return (self._queued, self._trial, self._probation) != (None, None, None)

    def offer(self, model: Model, request_step: int = 0, trial: int = 0,
              probation: int = 0) -> Optional[int]:
        """A model naming `request_step` (0: none), checked already unless `trial` > 0. Returns
        the step from whose tick on the answer to the pending request is used, or tried for
        `trial` samples (0: the next tick; it is held here until :meth:`due`), then on
        probation for `probation` samples once it flies (0: none), or None: any other model,
        which the caller uses (checked) from the next tick itself."""
        pending = self.trigger.pending      # once: a reset may forget it meanwhile
        if not request_step or pending is None or request_step != pending.step:
            return None
        start = pending.swap_step if self.lockstep else 0
        with self._lock:
            self._queued = (start, model, trial, probation)
        return start

    def refused(self, request_step: int) -> None:
        """The check refused a model naming `request_step`: if it answered the pending
        request, that request ends (the model in use stays; a later one may ask again)."""
        if self.answers(request_step):
            self.trigger.give_up()

    def waits(self, step: int) -> bool:
        """True if the tick of `step` must wait for the requested model (lockstep: its swap
        step has come and no answer is queued, tried or on probation)."""
        return self.lockstep and not self.holds_answer() and self.trigger.waits(step)

    def due(self, step: int, in_use: Optional[Model] = None) -> Optional[Model]:
        """The queued answer if the tick of `step` is to use it (then it is no longer queued),
        else None: the model in use (`in_use`) stays. An answer with a trial starts it at this
        tick instead (None)."""
        with self._lock:
            queued = self._queued
            if queued is None or step < queued[0]:
                return None
            self._queued = None
            if queued[2]:
                self._trial = (step,) + queued[1:]
                return None
        self._fly(step, queued[1], in_use, queued[3])
        return queued[1]

    def _fly(self, step: int, model: Model, replaced: Optional[Model], probation: int) -> None:
        """`model` is used from the tick of `step`: on probation, or answered for good."""
        if probation and replaced is not None:
            with self._lock:
                self._probation = (step, model, replaced, probation)
        else:
            self.trigger.answered(model.version)

    def trial_over(self, step: int) -> Optional[Tuple[int, Model]]:
        """(first step of its trial, the answer) if the tick of `step` ends the answer's trial
        (`trial` samples after its first: steps first..step scored), else None. The caller
        judges it and tells :meth:`judged`."""
        with self._lock:
            trial = self._trial
            if trial is None or step < trial[0] + trial[2]:
                return None
            self._trial = None
            self._after_trial = trial[3]
        return trial[0], trial[1]

    def judged(self, step: int, model: Model, ok: bool, in_use: Optional[Model] = None
               ) -> None:
        """The verdict on the answer whose trial the tick of `step` ended: it flies from this
        tick (on probation if it has one, `in_use` coming back if it fails), or it was
        refused (the request ends; the model in use stays)."""
        if ok:
            self._fly(step, model, in_use, self._after_trial)
        else:
            self.trigger.give_up()

    def probation_over(self, step: int) -> Optional[Tuple[int, Model, Model]]:
        """(first step of its probation, the flown answer, the model it replaced) if the tick
        of `step` ends the answer's probation (steps first..step scored), else None. The
        caller judges it and tells :meth:`kept`."""
        with self._lock:
            held = self._probation
            if held is None or step < held[0] + held[3]:
                return None
            self._probation = None
        return held[:3]

    def kept(self, model: Model, ok: bool) -> None:
        """The verdict at the end of `model`'s probation: kept (the request is answered), or
        reverted to the model it replaced (the request ends; a later one may ask again)."""
        if ok:
            self.trigger.answered(model.version)
        else:
            self.trigger.give_up()

    def retune(self, rebuild: Callable[[Model], Model]) -> None:
        """A live change of the tuning (builder thread): the queued or tried answer, and the
        model a flown one replaced, are rebuilt for it (`rebuild`: its QP for the new horizon,
        weights and bounds), as the model in use is, so that the tick of its step uses the
        tuning of every tick from then on."""
        for slot, index in (('_queued', 1), ('_trial', 1), ('_probation', 2)):
            with self._lock:
                held = getattr(self, slot)
            if held is None:
                continue
            model = rebuild(held[index])
            with self._lock:
                if getattr(self, slot) is held:     # not used or forgotten meanwhile
                    setattr(self, slot, held[:index] + (model,) + held[index + 1:])

    def new_episode(self) -> None:
        """A plant reset: the queued, tried or probation answer is forgotten (the trigger
        forgets the request)."""
        with self._lock:
            self._queued = self._trial = self._probation = None


__all__ = ['ModelSwap']

"""When a new model applies in the controller: the swap rules, without rclpy or threads.

A model built on the builder thread is used from the next tick, except the answer to the
pending adaptation request (``request_step`` r): under a lockstep plant it applies from the
tick of step r + swap_delay exactly (queued until then; that tick waits for it), in real time
from the next tick; offered with a trial of P samples it is tried from that tick instead (the
model in use goes on) and judged P samples later (:meth:`ModelSwap.trial_over`). A refused
model is never used; a refusal or a request given up after ``adapt_timeout`` ends the wait at
once. A live change rebuilds a queued or tried answer's QP; a plant reset forgets it. Threads:
:meth:`offer`, :meth:`answers`, :meth:`refused`, :meth:`retune` on the builder thread, the rest
on the executor thread; the queued answer is handed over under a lock.
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
            must name, and it is told when the answer is used (``answered``) or refused
            (``give_up``).
        lockstep: the plant is lockstep (the core sets it from plant_info).
    """

    def __init__(self, trigger: AdaptationTrigger, lockstep: bool = False):
        self.trigger = trigger
        self.lockstep = lockstep
        self._lock = threading.Lock()
        self._queued: Optional[Tuple[int, Model, int]] = None  # (from step, answer, trial)
        self._trial: Optional[Tuple[int, Model, int]] = None   # (from step, answer, samples)

    def answers(self, request_step: int) -> bool:
        """True if a model naming `request_step` (0: none) answers the pending request."""
        pending = self.trigger.pending
        return bool(request_step) and pending is not None and request_step == pending.step

    def offer(self, model: Model, request_step: int = 0, trial: int = 0) -> Optional[int]:
        """A model naming `request_step` (0: none), checked already unless `trial` > 0. Returns
        the step from whose tick on the answer to the pending request is used, or tried for
        `trial` samples (0: the next tick; it is held here until :meth:`due`), or None: any
        other model, which the caller uses (checked) from the next tick itself."""
        pending = self.trigger.pending      # once: a reset may forget it meanwhile
        if not request_step or pending is None or request_step != pending.step:
            return None
        start = pending.swap_step if self.lockstep else 0
        with self._lock:
            self._queued = (start, model, trial)
        return start

    def refused(self, request_step: int) -> None:
        """The check refused a model naming `request_step`: if it answered the pending
        request, that request ends (the model in use stays; a later one may ask again)."""
        if self.answers(request_step):
            self.trigger.give_up()

    def waits(self, step: int) -> bool:
        """True if the tick of `step` must wait for the requested model (lockstep: its swap
        step has come and no answer is queued or tried)."""
        return (self.lockstep and self._queued is None and self._trial is None
                and self.trigger.waits(step))

    def due(self, step: int) -> Optional[Model]:
        """The queued answer if the tick of `step` is to use it (then the request is answered
        and it is no longer queued), else None: the model in use stays. An answer with a trial
        starts it at this tick instead (None)."""
        with self._lock:
            queued = self._queued
            if queued is None or step < queued[0]:
                return None
            self._queued = None
            if queued[2]:
                self._trial = (step, queued[1], queued[2])
                return None
        self.trigger.answered(queued[1].version)
        return queued[1]

    def trial_over(self, step: int) -> Optional[Tuple[int, Model]]:
        """(first step of its trial, the answer) if the tick of `step` ends the answer's trial
        (`trial` samples after its first: steps first..step scored), else None. The caller
        judges it and tells :meth:`judged`."""
        with self._lock:
            trial = self._trial
            if trial is None or step < trial[0] + trial[2]:
                return None
            self._trial = None
        return trial[0], trial[1]

    def judged(self, model: Model, ok: bool) -> None:
        """The verdict on a tried answer: it flies from this tick (the request is answered), or
        it was refused (the request ends; the model in use stays)."""
        if ok:
            self.trigger.answered(model.version)
        else:
            self.trigger.give_up()

    def retune(self, rebuild: Callable[[Model], Model]) -> None:
        """A live change of the tuning (builder thread): the queued or tried answer is rebuilt
        for it (`rebuild`: its QP for the new horizon, weights and bounds), as the model in use
        is, so that the tick of its step uses the tuning of every tick from then on."""
        for slot in ('_queued', '_trial'):
            with self._lock:
                held = getattr(self, slot)
            if held is None:
                continue
            model = rebuild(held[1])
            with self._lock:
                if getattr(self, slot) is held:     # not used or forgotten meanwhile
                    setattr(self, slot, (held[0], model, held[2]))

    def new_episode(self) -> None:
        """A plant reset: the queued or tried answer is forgotten (the trigger forgets the
        request)."""
        with self._lock:
            self._queued = self._trial = None


__all__ = ['ModelSwap']

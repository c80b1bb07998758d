"""When a new model applies in the controller: the swap rules, without rclpy or threads.

A model built on the node's builder thread is used from the next tick, except the answer to
the pending adaptation request (``request_step`` r): under a lockstep plant it applies from
the tick of step r + swap_delay exactly (queued until then; that tick waits for it,
:meth:`ModelSwap.waits`), in real time from the next tick. A model the check refuses
(:mod:`~metampc_controller.model_check`, ``model_check``: requested / all / off) is never used;
a refused answer or a request given up after ``adapt_timeout`` ends the wait at once. A live
change rebuilds a queued answer's QP; a plant reset forgets it. Threads: :meth:`offer`,
:meth:`answers`, :meth:`refused`, :meth:`retune` on the builder thread, :meth:`due` and
:meth:`waits` on the executor thread; the queued answer is handed over under a lock.
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
        self._queued: Optional[Tuple[int, Model]] = None   # (from step, the answer)

    def answers(self, request_step: int) -> bool:
        """True if a model naming `request_step` (0: none) answers the pending request."""
        pending = self.trigger.pending
        return bool(request_step) and pending is not None and request_step == pending.step

    def offer(self, model: Model, request_step: int = 0) -> Optional[int]:
        """A checked model naming `request_step` (0: none). Returns the step from whose tick on
        the answer to the pending request is used (0: the next tick; it is held here until
        :meth:`due` hands it over), or None: any other model, which the caller uses from the
        next tick itself."""
        pending = self.trigger.pending      # once: a reset may forget it meanwhile
        if not request_step or pending is None or request_step != pending.step:
            return None
        start = pending.swap_step if self.lockstep else 0
        with self._lock:
            self._queued = (start, model)
        return start

    def refused(self, request_step: int) -> None:
        """The check refused a model naming `request_step`: if it answered the pending
        request, that request ends (the model in use stays; a later one may ask again)."""
        if self.answers(request_step):
            self.trigger.give_up()

    def waits(self, step: int) -> bool:
        """True if the tick of `step` must wait for the requested model (lockstep: its swap
        step has come and no answer is queued)."""
        return self.lockstep and self._queued is None and self.trigger.waits(step)

    def due(self, step: int) -> Optional[Model]:
        """The queued answer if the tick of `step` is to use it (then the request is answered
        and it is no longer queued), else None: the model in use stays."""
        with self._lock:
            queued = self._queued
            if queued is None or step < queued[0]:
                return None
            self._queued = None
        self.trigger.answered(queued[1].version)
        return queued[1]

    def retune(self, rebuild: Callable[[Model], Model]) -> None:
        """A live change of the tuning (builder thread): the queued answer is rebuilt for it
        (`rebuild`: its QP for the new horizon, weights and bounds), as the model in use is,
        so that the tick of its step uses the tuning of every tick from then on."""
        with self._lock:
            queued = self._queued
        if queued is None:
            return
        model = rebuild(queued[1])
        with self._lock:
            if self._queued is queued:      # not used or forgotten meanwhile
                self._queued = (queued[0], model)

    def new_episode(self) -> None:
        """A plant reset: the queued answer is forgotten (the trigger forgets the request)."""
        with self._lock:
            self._queued = None


__all__ = ['ModelSwap']

"""The lockstep plant's rules: when y_0 goes out, which input answers a step, how long a step
waits for it (one its controller holds included), and the sim-time stamp of every y. No
rclpy: the node (plant_node) asks these rules and does the publishing; times are seconds of a
monotonic wall clock that it passes in.
"""
from typing import Optional

# How long y must have had a subscriber and u a publisher before y_0 goes out, s: each side of
# a DDS match completes on its own time, and an answer to y_0 sent before the controller's
# writer matched our reader is lost.
GATE_SETTLE_S = 0.1


class Lockstep:
    """Start gate, stale inputs, input timeout, announced holds and sim-time stamps of one
    lockstep plant.

    * Start gate: y_0 goes out once the graph has been matched (y subscribed, u published)
      without a break for ``settle_s``, or ``start_timeout`` s after the gate opened
      (0: wait forever), or at a reset, whichever comes first; only once.
    * Stale inputs: an input answers the plant only after the start and only if its step is
      the plant's current step; any other is stale (ignored, counted).
    * Timeout: ``input_timeout`` s after each y without its answer, the plant steps with the
      held input (0: wait forever). The node arms a timer with :attr:`timeout_s` after each y.
    * Announced hold: a controller that holds its answer to the current step (it waits for
      a model it asked for, metampc_controller.model_gate) says so, with the longest it may
      hold it (hold_s); the step then waits hold_s + input_timeout s from that notice
      (:meth:`hold_timeout_s`), however long the timeout: the swap stays exact, and a plant
      whose controller died while holding still moves on.
    * Stamps: the n-th y published since start (n = 0, 1, ...; resets included) is stamped
      n * dt, in whole nanoseconds of the rounded dt, so sim time never goes back and does not
      drift with float sums.

    Args:
        dt: sample time, s (> 0).
        input_timeout: s to wait for the answer to a y; 0 waits forever.
        start_timeout: s after `now` to publish y_0 without a match; 0 waits forever.
        now: when the gate opens (the node's start), s.
        settle_s: how long the match must hold, s.

    Attributes:
        started: y_0 is out; from now on inputs answer steps.
        tick: index of the last y published since start (-1: none yet).
    """

    def __init__(self, dt: float, input_timeout: float, start_timeout: float, now: float,
                 settle_s: float = GATE_SETTLE_S):
        self._dt_ns = round(dt * 1e9)
        self._input_timeout = input_timeout
        self._start_timeout = start_timeout
        self._settle_s = settle_s
        self._gate_since = now
        self._matched_since: Optional[float] = None
        self.started = False
        self.tick = -1

    @property
    def timeout_s(self) -> Optional[float]:
        """Wait for the answer to each y, s; None: wait forever."""
        return self._input_timeout if self._input_timeout > 0 else None

    def hold_timeout_s(self, step: int, current: int, hold_s: float) -> Optional[float]:
        """A controller holds its answer to `step` for at most `hold_s` s (finite, >= 0): the
        wait from now for the answer to the current step, s; None if that changes nothing
        (another step, before the start, or no timeout: the plant waits forever anyway)."""
        if not self.answers(step, current) or self.timeout_s is None:
            return None
        return hold_s + self._input_timeout

    def gate(self, now: float, matched: bool) -> bool:
        """A look at the graph at `now`; True if y_0 is to go out now (then call :meth:`start`).

        Args:
            matched: y has a subscriber and u a publisher.
        """
        if self.started:
            return False
        if not matched:
            self._matched_since = None
        elif self._matched_since is None:
            self._matched_since = now
        settled = self._matched_since is not None and now - self._matched_since >= self._settle_s
        return settled or 0 < self._start_timeout <= now - self._gate_since

    def start(self) -> None:
        """y_0 goes out (through the gate or a reset); idempotent."""
        self.started = True

    def answers(self, step: int, current: int) -> bool:
        """True if an input for `step` answers the plant at step `current`; else it is stale."""
        return self.started and step == current

    def published(self) -> None:
        """A y went out: the stamp moves on by dt."""
        self.tick += 1

    @property
    def stamp_ns(self) -> int:
        """Sim time of the last y, ns (0 before the first)."""
        return max(self.tick, 0) * self._dt_ns

"""The machine bridge's rules, one sample, answer and tick at a time. No rclpy.

Ticks: step k at t_k = t_0 + k dt (t_0: the first tick; :func:`sampling.grid_step`). At t_k
each topic gives its held sample (:mod:`.sampling`); when all are fresh, y_k goes out with
u_applied_k (the input written last at or before t_k: held over (k-1, k]) and whether it was
clipped; else no y_k: the step is skipped. The command: the controller's answer, if it answers a
step published since the machine's samples last became fresh and newer than the last one taken,
clipped to [min, max] and written at once; the safe value, written at every tick, while the
machine's samples are stale ('stale') or no answer came for stale_timeout s ('waiting').
docs/bridge.md.
"""
from dataclasses import dataclass
import math
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from metampc_plant.machine_mapping import MachineMapping
from metampc_plant.sampling import grid_step, SampleStream

FOLLOWING, WAITING, STALE = 'following', 'waiting', 'stale'
DROPPED, OFFSET = 'dropped_samples', 'clock_offsets'     # what a sample's warning is about


@dataclass
class Tick:
    """What one tick decided.

    Attributes:
        step, time: k and t_k, s.
        y: y_k (n_y,) to publish, or None (a topic is stale: nothing to publish).
        u_applied: the input held over (k-1, k] (n_u,); saturated: it was clipped.
        state: FOLLOWING (the controller's answers go out), WAITING (no answer for
            stale_timeout s) or STALE (a topic is stale); reason: why not FOLLOWING ('').
        previous: the state before (the previous tick's, or the answer's that ended it; ''
            at the first tick).
        write: the input to write now (the safe value), or None.
        ages: per topic, the age of its held sample at t_k, s (inf: none yet).
    """

    step: int
    time: float
    y: Optional[np.ndarray]
    u_applied: np.ndarray
    saturated: bool
    state: str
    reason: str
    previous: str
    write: Optional[np.ndarray]
    ages: Tuple[float, ...]

    @property
    def changed(self) -> bool:
        return self.state != self.previous


@dataclass
class Answer:
    """What became of one controller answer: `write` (the clipped input, written now) or
    None with `why`; `resumed`: it ended a WAITING state."""

    write: Optional[np.ndarray]
    why: str = ''
    resumed: bool = False


class BridgeCore:
    """The rules of the module docstring for one :class:`MachineMapping`; times in s on the
    bridge's clock (the stamps' clock)."""

    def __init__(self, mapping: MachineMapping):
        self.mapping = mapping
        self.state = ''                 # none before the first tick
        self._streams = [SampleStream() for _ in mapping.topics]
        # What was written, [u..., clipped]; before the first write the safe value is assumed.
        self._written = SampleStream()
        self._written.add(-math.inf, [*mapping.safe, 0.0])
        self._t0: Optional[float] = None
        self._step: Optional[int] = None
        self._fresh_from: Optional[int] = None     # first step of the current fresh period
        self._answered = -1                         # step of the last answer taken
        self._answer_time: Optional[float] = None   # when it came (None: none since fresh)

    def sample(self, index: int, msg: Any, received: float) -> Tuple[str, str]:
        """Take a message of topic `index` (mapping.topics) that arrived at `received`;
        ('', '') or (DROPPED, why: a field missing, a value not finite) or (OFFSET, a stamp
        farther than stale_timeout from the arrival: taken, but the clocks may differ)."""
        topic = self.mapping.topics[index]
        try:
            values = self.mapping.output_values(topic, msg)
            stamp = self.mapping.stamp(topic, msg, received)
        except ValueError as err:
            return DROPPED, f'{topic.topic}: sample dropped ({err})'
        if not (np.all(np.isfinite(values)) and math.isfinite(stamp)):
            return DROPPED, (f'{topic.topic}: sample dropped (not finite: {values.tolist()}, '
                             f'stamp {stamp})')
        self._streams[index].add(stamp, values)
        offset = stamp - received
        if abs(offset) > self.mapping.stale_timeout:
            return OFFSET, (f'{topic.topic}: a sample stamped {offset:+.3f} s from its arrival, '
                            'beyond stale_timeout: do the machine\'s and the bridge\'s clocks '
                            'agree? (stamp: receive takes the arrival time)')
        return '', ''

    def answer(self, step: int, u: Any, now: float) -> Answer:
        """Take the controller's answer to `step` (ControlInput) arriving at `now`."""
        if self.state == STALE or self._fresh_from is None:
            return Answer(None, 'the machine\'s samples are stale')
        if not self._fresh_from <= step <= self._step:
            return Answer(None, f'step {step} is not one published since the samples are '
                                f'fresh (steps {self._fresh_from}-{self._step})')
        if step <= self._answered:
            return Answer(None, f'step {step} was answered already')
        u = np.asarray(u, dtype=float)
        n_u = len(self.mapping.command.inputs)
        if u.shape != (n_u,) or not np.all(np.isfinite(u)):
            return Answer(None, f'expected {n_u} finite value(s), got {u.tolist()}')
        clipped = np.clip(u, self.mapping.u_min, self.mapping.u_max)
        self._answered, self._answer_time = step, now
        self._written.add(now, [*clipped, float(np.any(clipped != u))])
        resumed = self.state == WAITING
        if resumed:
            self.state = FOLLOWING
        return Answer(clipped, resumed=resumed)

    def tick(self, now: float) -> Tick:
        """The tick of the bridge's timer at `now` (see the module docstring)."""
        mapping = self.mapping
        if self._t0 is None:
            self._t0 = now
        self._step = grid_step(self._step, now - self._t0, mapping.dt)
        t = self._t0 + self._step * mapping.dt
        held = [stream.at(t) for stream in self._streams]
        ages = tuple(age for _, age in held)
        y, reason = None, self._stale_reason(ages)
        if reason:
            state, self._fresh_from, self._answer_time = STALE, None, None
        else:
            if self._fresh_from is None:
                self._fresh_from = self._step
            y = np.empty(len(mapping.outputs))
            for topic, (values, _) in zip(mapping.topics, held):
                y[list(topic.outputs)] = values
            state, reason = self._answer_state(t)
        written = self._written.at(t)[0]
        write = None
        if state != FOLLOWING:
            write = mapping.safe
            self._written.add(now, [*write, 0.0])
        previous, self.state = self.state, state
        return Tick(self._step, t, y, written[:-1], bool(written[-1]), state, reason, previous,
                    write, ages)

    def _stale_reason(self, ages: Tuple[float, ...]) -> str:
        for topic, age in zip(self.mapping.topics, ages):
            if math.isinf(age):
                return f'no sample on {topic.topic} yet'
            if age > self.mapping.stale_timeout:
                return f'no sample on {topic.topic} for {age:.3f} s'
        return ''

    def _answer_state(self, t: float) -> Tuple[str, str]:
        if self._answer_time is None:
            return WAITING, 'no input from the controller yet'
        silent = t - self._answer_time
        if silent > self.mapping.stale_timeout:
            return WAITING, f'no input from the controller for {silent:.3f} s'
        return FOLLOWING, ''


def type_mismatches(mapping: MachineMapping, writers: Dict[str, Sequence[str]],
                    readers: Sequence[str]) -> List[str]:
    """One line for each topic of `mapping` that the graph carries in another type than the
    mapping's: an output topic whose writers (`writers`: topic -> the types of its publishers)
    all use other types (no sample of it can come: the bridge waits in its safe state), the
    command topic with a reader of another type (`readers`: the types of its subscriptions; it
    gets no command)."""
    lines = []
    for topic in mapping.topics:
        types = sorted(set(writers.get(topic.topic, ())))
        if types and topic.type not in types:
            lines.append(f'{topic.topic} carries {", ".join(types)}, not {topic.type} as the '
                         'mapping says: no sample of it can come (is the type in the mapping '
                         'right?)')
    command = mapping.command
    others = sorted(set(readers) - {command.type})
    if others:
        lines.append(f'{command.topic} is read as {", ".join(others)}: the commands go out as '
                     f'{command.type}, as the mapping says, and reach no reader of another '
                     'type (is the type in the mapping right?)')
    return lines

"""The experiment's events: one dataclass per event, the topic they go on, their encoding.

The orchestrator publishes one event per phase (:meth:`ExperimentClient.event
<metampc_bringup.orchestration.experiment_client.ExperimentClient.event>`), the recorder stores
them with the run, and the reports read them back with :func:`read_events`. On the wire a
std_msgs/String per event holding one JSON object ``{"event": KIND, "wall_time": s, the fields
in the order declared}``; older recordings without ``run`` and ``theta_schedule`` read as '' and
[], without an adapt event's ``fallback`` as ''. No rclpy here: a report imports this module.
The events: docs/experiments.md.
"""
import json
import time
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Dict, List

EVENTS_TOPIC = 'experiment_events'


@dataclass(kw_only=True)
class ExperimentEvent:
    """What every event holds: its wall-clock publication time (s since the epoch)."""

    KIND: ClassVar[str] = ''
    wall_time: float = field(default_factory=time.time)

    def record(self) -> Dict[str, Any]:
        """The event as the JSON object on the wire, keys in wire order."""
        return {'event': self.KIND, **{f.name: getattr(self, f.name) for f in fields(self)}}

    def encode(self) -> str:
        """The text of the event's std_msgs/String."""
        return json.dumps(self.record(), allow_nan=True)


@dataclass(kw_only=True)
class Start(ExperimentEvent):
    """The graph is ready: the seed, its theta*, the methods compared, the nodes started."""

    KIND: ClassVar[str] = 'start'
    seed: int
    theta: List[float]
    methods: List[str]
    nodes: List[str]


@dataclass(kw_only=True)
class CollectStart(ExperimentEvent):
    """D_target's collection began at sim time `stamp` (s) on the plant at `theta`."""

    KIND: ClassVar[str] = 'collect_start'
    stamp: float
    theta: List[float]


@dataclass(kw_only=True)
class CollectEnd(ExperimentEvent):
    """The collection ended at sim time `stamp` (s): valid samples, plant escapes (resets)."""

    KIND: ClassVar[str] = 'collect_end'
    stamp: float
    samples: int
    escapes: int


@dataclass(kw_only=True)
class BufferingStopped(ExperimentEvent):
    """The learner's D_target counts when its buffering stopped (SetBuffering's answer)."""

    KIND: ClassVar[str] = 'buffering_stopped'
    kept: int
    skipped: int
    lost: int


@dataclass(kw_only=True)
class MetaTrained(ExperimentEvent):
    """A meta_train call: the request's fields and the answer's (loss in normalised units)."""

    KIND: ClassVar[str] = 'meta_train'
    method: str
    request: Dict[str, Any]
    model_version: int
    final_loss: float
    loss_curve: List[float]
    message: str


@dataclass(kw_only=True)
class Adapted(ExperimentEvent):
    """An adapt call: the request's fields and the answer's (losses in normalised units;
    `fallback`: see Adapt.srv, '' in recordings made before it)."""

    KIND: ClassVar[str] = 'adapt'
    method: str
    request: Dict[str, Any]
    model_version: int
    loss_before: float
    loss_after: float
    loss_curve: List[float]
    message: str
    fallback: str = ''        # the learner's gain check published this method's model instead


@dataclass(kw_only=True)
class TrackEvent(ExperimentEvent):
    """What both ends of a tracking run hold: the method and the run's name."""

    method: str
    run: str = ''

    @property
    def run_name(self) -> str:
        """The run's name: `run` (e.g. 'imaml/triggered'), or in recordings made before drift
        runs, the method."""
        return self.run or self.method


@dataclass(kw_only=True)
class TrackStart(TrackEvent):
    """A tracking run began: y_0 stamped `stamp` (sim s), `steps` steps asked of
    `controller` holding `model_version` (0: the NMPC), under the plant's `theta_schedule`."""

    KIND: ClassVar[str] = 'track_start'
    controller: str
    model_version: int
    stamp: float
    steps: int
    theta_schedule: List[float] = field(default_factory=list)


@dataclass(kw_only=True)
class TrackEnd(TrackEvent):
    """A tracking run ended at sim time `stamp` (s) after `steps` steps, or at the first
    diverged sample."""

    KIND: ClassVar[str] = 'track_end'
    stamp: float
    steps: int
    diverged: bool


@dataclass(kw_only=True)
class Done(ExperimentEvent):
    """Every phase ran: wall time per phase (s), episodes restarted for a missed y_0."""

    KIND: ClassVar[str] = 'done'
    timings: Dict[str, float]
    episode_restarts: int


KINDS = {cls.KIND: cls for cls in (Start, CollectStart, CollectEnd, BufferingStopped,
                                   MetaTrained, Adapted, TrackStart, TrackEnd, Done)}


def from_record(record: Dict[str, Any]) -> ExperimentEvent:
    """The event of a JSON object from the wire; ValueError naming what does not fit."""
    values = dict(record)
    kind = values.pop('event', None)
    cls = KINDS.get(kind)
    if cls is None:
        raise ValueError(f'unknown experiment event {kind!r} (known: {", ".join(KINDS)})')
    if 'wall_time' not in values:    # a writer's default, never a reader's
        raise ValueError(f'experiment event {kind!r} without wall_time')
    try:
        return cls(**values)
    except TypeError as err:
        raise ValueError(f'experiment event {kind!r}: {err}') from None


def decode(text: str) -> ExperimentEvent:
    """The event of a std_msgs/String's text."""
    return from_record(json.loads(text))


def read_events(recording) -> List[ExperimentEvent]:
    """The experiment events of a recording (:class:`metampc_recording.recording_reader.
    Recording`: every topic named ``.../experiment_events``), in recorded order."""
    topics = [t.name for t in recording.topics.values()
              if t.name.rsplit('/', 1)[-1] == EVENTS_TOPIC]
    return [decode(msg.data) for _, _, msg in recording.decoded(topics)]

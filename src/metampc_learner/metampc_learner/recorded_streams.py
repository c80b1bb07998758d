"""A machine's recording read through its mapping file: stamped streams of y and of u.

A bag (rosbag2 folder of MCAP or sqlite3 storage, or one ``.mcap`` / ``.db3`` file; read by
`rosbags`; an MCAP file cut short, e.g. by a killed recorder, by metampc_recording's reader up
to its last complete chunk) gives, per output topic of the mapping, each message's stamp (the
mapping's stamp rule; the log time for ``receive``) and outputs, and the command topic's inputs
stamped by their log time. A CSV (a header row of column names) gives the same from its
columns: the outputs' and inputs' ``name``, holding the fields' values (y_i = scale * column +
offset, u_j = (column - offset) / scale), stamped by a time column (s) or one row per dt. A
value that cannot be read (a sequence too short for the field's index, an empty cell) is NaN.
:class:`RecordingError` is one line naming what is wrong. docs/offline_adaptation.md.
"""
import csv
import glob
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

from metampc_plant.machine_mapping import MachineMapping

TIME_COLUMN = 'time'    # the CSV's time column when it has one of that name


class RecordingError(ValueError):
    """The recording cannot be read with the mapping; the text is one line."""


@dataclass
class Stream:
    """Samples of one stream in stamp order: stamps (n,) s, values (n, m); `columns`: which
    outputs (or inputs) of the mapping the m values are."""

    stamps: np.ndarray
    values: np.ndarray
    columns: Tuple[int, ...]


@dataclass
class Recorded:
    """What a recording holds for the mapping.

    Attributes:
        outputs: one stream per output topic (bag) or one for all outputs (CSV).
        command: the inputs u (n, n_u), stamped by log time (bag) or row time (CSV).
        kind: 'bag' or 'csv'; clock: how the samples are stamped, in words.
        read: messages (rows) read per topic (column group); unreadable: of them, those
            with a value that could not be read (NaN).
        cut_short: '' for a finished recording; else what was read of one cut short.
    """

    outputs: List[Stream]
    command: Stream
    kind: str
    clock: str
    read: Dict[str, int]
    unreadable: Dict[str, int]
    cut_short: str = ''


def _stream(stamps: Sequence[float], values: Sequence[np.ndarray], width: int,
            columns: Tuple[int, ...]) -> Stream:
    """A stream sorted by stamp (stable: equal stamps keep their order)."""
    stamps = np.asarray(stamps, dtype=float)
    values = np.asarray(values, dtype=float).reshape(len(stamps), width)
    order = np.argsort(stamps, kind='stable')
    return Stream(stamps[order], values[order], columns)


def read_streams(path: str, mapping: MachineMapping, time_column: Optional[str] = None,
                 progress: bool = False) -> Recorded:
    """A CSV (name ending ``.csv``) or a bag at `path`; `time_column`: the CSV's (None: `time`
    if it has one, else one row per dt); `progress`: a progress bar on a terminal (bags)."""
    if path.lower().endswith('.csv'):
        return read_csv(path, mapping, time_column)
    if time_column is not None:
        raise RecordingError(f'{path}: a time column is for a CSV, not a bag')
    return read_bag(path, mapping, progress)


def _reader(path: str):
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag2 import ReaderError
    if not os.path.exists(path):
        raise RecordingError(f'{path}: no such file or folder')
    try:
        reader = AnyReader([Path(path)])
        reader.open()
    except (OSError, AnyReaderError, ReaderError) as err:
        raise RecordingError(f'{path}: not a readable bag ({" ".join(str(err).split())})') \
            from None
    return reader


def read_bag(path: str, mapping: MachineMapping, progress: bool = False) -> Recorded:
    """The mapping's topics of a bag (see the module docstring).

    Raises:
        RecordingError: no bag there, a mapping topic not in it or of another type, or its
            messages lack a field of the mapping (the bag's type differs from the installed).
    """
    cut = cut_mcap(path)
    if cut is not None:
        return _read_cut_mcap(cut, path, mapping, progress)
    reader = _reader(path)
    try:
        _check_topics({c.topic: c.msgtype for c in reader.connections}, path, mapping)
        connections = [c for c in reader.connections if c.topic in _keys(mapping)]
        messages = ((c.topic, log_time, reader.deserialize(raw, c.msgtype))
                    for c, log_time, raw in reader.messages(connections=connections))
        return _read_messages(messages, sum(c.msgcount for c in connections), path, mapping,
                              progress)
    finally:
        reader.close()


def cut_mcap(path: str) -> Optional[str]:
    """The MCAP file at `path` (the file, or a folder's only ``.mcap``) if it lacks its end
    (its writer never finished it), else None."""
    from metampc_recording.recording_reader import finished, resolve_recording
    files = [path] if os.path.isfile(path) else sorted(glob.glob(os.path.join(path, '*.mcap')))
    if len(files) != 1 or not files[0].lower().endswith('.mcap'):
        return None
    try:
        resolve_recording(files[0])     # starts as an MCAP file does
    except ValueError:
        return None                     # not MCAP: rosbags says what it is
    return None if finished(files[0]) else files[0]


def _read_cut_mcap(file: str, path: str, mapping: MachineMapping, progress: bool) -> Recorded:
    """An MCAP file cut short: every message of its complete chunks (metampc_recording's
    stream reader needs no summary), decoded with the schemas stored in it."""
    from metampc_recording.recording_reader import read_recording as read_mcap
    recording = read_mcap(file, messages=False)
    _check_topics({t.name: t.type_name for t in recording.topics.values()}, path, mapping)
    keys = _keys(mapping)
    messages = ((raw.topic, raw.log_time, msg) for _, raw, msg in recording.decoded(keys))
    recorded = _read_messages(messages, sum(recording.topics[k].count for k in keys), path,
                              mapping, progress)
    recorded.cut_short = (f'{file} was cut short (no end: its writer did not finish it); '
                          f'read its {recording.message_count} messages up to its last '
                          'complete chunk')
    return recorded


def _wanted(mapping: MachineMapping) -> List[Tuple[str, str, str]]:
    """(key in the mapping file, topic, type) of each topic the mapping reads."""
    return [*((f'outputs[{t.outputs[0]}]', t.topic, t.type) for t in mapping.topics),
            ('command', mapping.command.topic, mapping.command.type)]


def _keys(mapping: MachineMapping) -> Dict[str, str]:
    """The mapping's topics, each with its key in the mapping file (for messages)."""
    return {topic: key for key, topic, _ in _wanted(mapping)}


def _check_topics(recorded: Dict[str, str], path: str, mapping: MachineMapping) -> None:
    """RecordingError if a topic of the mapping is not among `recorded` ({topic: type}) or is
    of another type there."""
    for key, topic, type_name in _wanted(mapping):
        if topic not in recorded:
            listed = ', '.join(f'{n} ({t})' for n, t in sorted(recorded.items())) or 'none'
            raise RecordingError(f'{key}.topic: {topic} is not in {path} (its topics: '
                                 f'{listed})')
        if recorded[topic] != type_name:
            raise RecordingError(f'{key}.type: {topic} is {recorded[topic]} in {path}, '
                                 f'not {type_name}')


def _read_messages(messages: Iterable[Tuple[str, int, Any]], total: int, path: str,
                   mapping: MachineMapping, progress: bool) -> Recorded:
    """Recorded from `messages`: (topic, log time in ns, decoded message) of the mapping's
    topics, `total` of them (for the progress bar)."""
    from tqdm import tqdm
    keys = _keys(mapping)
    index = {t.topic: i for i, t in enumerate(mapping.topics)}
    n_u = len(mapping.command.inputs)
    stamps: Dict[str, List[float]] = {name: [] for name in keys}
    values: Dict[str, List[np.ndarray]] = {name: [] for name in keys}
    unreadable = dict.fromkeys(keys, 0)
    bar = tqdm(messages, desc=f'reading {path}', unit='msg', total=total,
               disable=not progress, leave=False)
    for name, log_time, msg in bar:
        received = 1e-9 * log_time
        try:
            if name == mapping.command.topic:
                stamp, read = received, _values(lambda: mapping.command_values(msg), n_u)
            else:
                topic = mapping.topics[index[name]]
                stamp = mapping.stamp(topic, msg, received)
                read = _values(lambda: mapping.output_values(topic, msg), len(topic.outputs))
        except AttributeError as err:
            raise RecordingError(f'{keys[name]}: the messages of {name} in {path} have no '
                                 f'field {err.name!r} (its type there differs from the '
                                 'installed one)') from None
        unreadable[name] += int(not np.all(np.isfinite(read)))
        stamps[name].append(stamp)
        values[name].append(read)
    outputs = [_stream(stamps[t.topic], values[t.topic], len(t.outputs), t.outputs)
               for t in mapping.topics]
    command = _stream(stamps[mapping.command.topic], values[mapping.command.topic], n_u,
                      tuple(range(n_u)))
    clock = ', '.join(f'{t.topic}: {t.stamp.text if t.stamp else "log time"}'
                      for t in mapping.topics) + f', {mapping.command.topic}: log time'
    return Recorded(outputs, command, 'bag', clock, {k: len(v) for k, v in stamps.items()},
                    unreadable)


def _values(read: Callable[[], np.ndarray], width: int) -> np.ndarray:
    """`read()`, or NaN (width,) when a sequence is too short for the field's index."""
    try:
        return read()
    except ValueError:
        return np.full(width, np.nan)


def _number(cell: str, path: str, row: int, column: str) -> float:
    text = cell.strip()
    if not text:
        return math.nan
    try:
        return float(text)
    except ValueError:
        raise RecordingError(f'{path}: row {row}, column {column!r}: {text!r} is no number') \
            from None


def read_csv(path: str, mapping: MachineMapping, time_column: Optional[str] = None
             ) -> Recorded:
    """The mapping's outputs and inputs from the named columns of a CSV (module docstring).

    Raises:
        RecordingError: no such file, a column missing, a row with fewer cells than the
            header, a cell that is no number, a time that is not finite or not after the row
            before.
    """
    try:
        with open(path, newline='', encoding='utf-8') as f:
            rows = list(csv.reader(f))
    except OSError as err:
        raise RecordingError(f'cannot read {path}: {err.strerror}') from None
    except (UnicodeDecodeError, csv.Error) as err:
        raise RecordingError(f'{path} is no CSV text: {err}') from None
    if not rows:
        raise RecordingError(f'{path}: empty (a header row of column names is needed)')
    header = [name.strip() for name in rows[0]]
    body = [(n, r) for n, r in enumerate(rows[1:], 2) if any(cell.strip() for cell in r)]
    for n, r in body:
        if len(r) < len(header):
            raise RecordingError(f'{path}: row {n} has {len(r)} cell(s), the header '
                                 f'{len(header)}')
    wanted = ([(f'outputs[{i}].name', o.name) for i, o in enumerate(mapping.outputs)]
              + [(f'command.inputs[{j}].name', i.name)
                 for j, i in enumerate(mapping.command.inputs)])
    if time_column is None and TIME_COLUMN in header:
        time_column = TIME_COLUMN
    if time_column is not None:
        wanted.append(('the time column', time_column))
    for key, name in wanted:
        if name not in header:
            raise RecordingError(f'{path}: no column {name!r} ({key}; its columns: '
                                 f'{", ".join(header)})')
    where = {name: header.index(name) for _, name in wanted}
    table = np.array([[_number(r[where[name]], path, n, name) for _, name in wanted]
                      for n, r in body], dtype=float).reshape(len(body), len(wanted))
    n_y = len(mapping.outputs)
    n_u = len(mapping.command.inputs)
    if time_column is None:
        times, clock = mapping.dt * np.arange(len(body)), f'one row per dt = {mapping.dt:g} s'
    else:
        times, clock = table[:, -1], f'column {time_column!r}, s'
        bad = np.flatnonzero(~np.isfinite(times) | (np.diff(times, prepend=-np.inf) <= 0))
        if bad.size:
            k = bad[0]
            raise RecordingError(f'{path}: row {body[k][0]}: the time {float(times[k])!r} is '
                                 + ('not finite' if not np.isfinite(times[k]) else
                                    f'not after the row before ({float(times[k - 1])!r})'))
    y = table[:, :n_y] * [o.scale for o in mapping.outputs] + [o.offset
                                                               for o in mapping.outputs]
    inputs = mapping.command.inputs
    u = (table[:, n_y:n_y + n_u] - [i.offset for i in inputs]) / [i.scale for i in inputs]
    rows_read = {'outputs': len(body), 'inputs': len(body)}
    unreadable = {'outputs': int(np.sum(~np.all(np.isfinite(y), axis=1))),
                  'inputs': int(np.sum(~np.all(np.isfinite(u), axis=1)))}
    return Recorded([Stream(times, y, tuple(range(n_y)))], Stream(times, u, tuple(range(n_u))),
                    'csv', clock, rows_read, unreadable)


__all__ = ['RecordingError', 'Stream', 'Recorded', 'read_streams', 'read_bag', 'read_csv',
           'TIME_COLUMN']

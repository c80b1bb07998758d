"""Analysis of a run from its recording alone: series, metrics, plots, report.json.

:func:`analyse` reads an MCAP file or a run folder holding one
(:mod:`~metampc_recording.recording_reader`), streamed message by message, rebuilds the series
(:mod:`~metampc_bringup.analysis.run_series`), computes the metrics
(:mod:`~metampc_bringup.analysis.metrics`; ``tracked_outputs`` of the recorder's ``metampc``
record, copied into the report, says which outputs track) and writes ``report.json`` and the
plots next to the recording. Refuses (FileExistsError, before writing anything) to overwrite a
``report.json`` it did not write (``generator`` not :data:`GENERATOR`). The report's fields:
docs/recording.md. No rclpy here.
"""
import json
import math
import os
from typing import Dict, List, Optional, Sequence

from metampc_bringup.analysis.metrics import Bounds, compute_metrics
from metampc_bringup.analysis.plots import write_plots
from metampc_bringup.analysis.run_series import DEFAULT_TOPICS, RunSeries, SeriesBuilder
from metampc_recording.recording_reader import read_recording, Recording, RecordedTopic

REPORT_NAME = 'report.json'
GENERATOR = 'metampc_bringup.analysis'    # the report's 'generator' field


def select_topics(topics: Dict[str, RecordedTopic],
                  overrides: Optional[Dict[str, str]] = None) -> Dict[str, str]:
    """Topic to analyse per metampc message type.

    A type carried by one topic takes it; by several, the one whose last name token is the
    default name (docs/architecture.md: 'y', 'u', 'mpc_status', ...), else ValueError.

    Args:
        topics: the recording's topics.
        overrides: type name -> topic name, chosen by the caller.
    """
    chosen: Dict[str, str] = {}
    for type_name, default in DEFAULT_TOPICS.items():
        if overrides and type_name in overrides:
            chosen[type_name] = overrides[type_name]
            continue
        candidates = sorted(t.name for t in topics.values() if t.type_name == type_name)
        if len(candidates) > 1:
            candidates = [c for c in candidates if c.rsplit('/', 1)[-1] == default]
            if len(candidates) != 1:
                raise ValueError(f'several topics carry {type_name}; choose one with overrides')
        if candidates:
            chosen[type_name] = candidates[0]
    return chosen


def series_from_recording(recording: Recording,
                          overrides: Optional[Dict[str, str]] = None) -> RunSeries:
    """The run's series from the selected topics of a recording (log-time order); streamed
    message by message into a SeriesBuilder when the recording was read without its
    messages."""
    selected = select_topics(recording.topics, overrides)
    builder = SeriesBuilder()
    for topic, raw, msg in recording.decoded(selected.values()):
        builder.add(topic.type_name, msg, raw.log_time)
    return builder.build()


def _check_report_path(path: str) -> None:
    """FileExistsError if `path` exists and is not a report of this module."""
    if not os.path.exists(path):
        return
    try:
        with open(path) as f:
            generator = json.load(f).get('generator')
    except (OSError, ValueError, AttributeError):
        generator = None
    if generator != GENERATOR:
        raise FileExistsError(f'{path} exists and is not a replay report; not overwriting it '
                              '(choose another output folder)')


def json_safe(value):
    """JSON-safe copy: non-finite floats become None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def analyse(path: str, out_dir: Optional[str] = None, tracked: Optional[Sequence[int]] = None,
            u_bounds: Optional[Bounds] = None, plots: bool = True,
            overrides: Optional[Dict[str, str]] = None,
            report_name: Optional[str] = REPORT_NAME) -> Dict:
    """Analyse one recording and write its report and plots.

    Args:
        path: MCAP file or run folder with one ``.mcap``.
        out_dir: where report and plots go (default: the recording's folder).
        tracked: output indices with a reference (default: the run config's
            ``tracked_outputs``, else those the controller weights, MpcStatus.q > 0, else all
            outputs).
        u_bounds: (u_min, u_max) for the bound check (default: from PlantInfo).
        plots: write the PNGs.
        overrides: type name -> topic, see :func:`select_topics`.
        report_name: file name of the JSON report in `out_dir`; None writes no report.

    Returns:
        The report (JSON-ready, non-finite floats as None): ``generator``, ``recording``
        (file, completeness, topics and counts, times), ``config`` (the run configuration),
        ``metrics`` (see :func:`metrics.compute_metrics`), ``plots`` (file names).

    Raises:
        FileNotFoundError, ValueError: see :func:`recording_reader.resolve_recording`; a
            recording without messages; a tracked output the plant does not have.
        FileExistsError: `out_dir` holds a report_name file that is not a report of this
            module (nothing is written then).
    """
    recording = read_recording(path, messages=False)    # streamed: any size in bounded memory
    if not recording.message_count:
        raise ValueError(f'{recording.path} holds no message ({os.path.getsize(recording.path)} '
                         'bytes: cut short before the first one?); nothing to analyse')
    config = recording.run_config()
    out_dir = out_dir or os.path.dirname(os.path.abspath(recording.path))
    if report_name:
        _check_report_path(os.path.join(out_dir, report_name))
    os.makedirs(out_dir, exist_ok=True)
    if tracked is None and 'tracked_outputs' in config:
        tracked = [int(i) for i in config['tracked_outputs']]
    series = series_from_recording(recording, overrides)
    if tracked is None and series.status.q.size == series.n_y:
        # No run metadata (a by-hand recording): the outputs the controller weighted.
        tracked = [i for i, weight in enumerate(series.status.q) if weight > 0]
    bad = [i for i in tracked or () if not 0 <= int(i) < series.n_y]
    if bad:
        raise ValueError(f'tracked output(s) {bad} out of range: the plant has {series.n_y} '
                         f'outputs, 0..{series.n_y - 1}')
    metrics = compute_metrics(series, tracked, u_bounds)
    written: List[str] = []
    if plots:
        bounds = metrics['input_bounds']
        written = write_plots(series, out_dir,
                              (bounds['u_min'], bounds['u_max']) if bounds else None,
                              metrics['tracking']['tracked_outputs'])
    start, end = recording.start_ns, recording.end_ns
    report = json_safe({
        'generator': GENERATOR,
        'recording': {
            'path': os.path.abspath(recording.path),
            'complete': recording.complete,
            'message_count': recording.message_count,
            'topics': {t.name: {'type': t.type_name, 'count': t.count}
                       for t in recording.topics.values()},
            'start_ns': start,
            'end_ns': end,
            'duration_s': (end - start) * 1e-9,
        },
        'config': config,
        'metrics': metrics,
        'plots': [os.path.basename(p) for p in written],
    })
    if report_name:
        with open(os.path.join(out_dir, report_name), 'w') as f:
            json.dump(report, f, indent=2, sort_keys=True)
    return report


def _fmt(value) -> str:
    if value is None:
        return '-'
    if isinstance(value, float):
        return f'{value:.6g}'
    return str(value)


RANGES_SHOWN = 3    # episodes whose step range a summary line names, at most


def _ranges(ranges: List[Dict]) -> str:
    """'steps 100-499 (episode 0), 0-35 (episode 1)': one range per episode."""
    shown = [f"{r['first_step']}-{r['last_step']} (episode {r['episode']})"
             for r in ranges[:RANGES_SHOWN]]
    more = len(ranges) - RANGES_SHOWN
    return 'steps ' + ', '.join(shown) + (f', ... {more} more episodes' if more > 0 else '')


def _foreign(foreign: Dict) -> str:
    """'0', or '2 (steps 3, 7)'."""
    if not foreign['count']:
        return '0'
    steps = ', '.join(str(k) for k in foreign['steps'])
    more = ', ...' if foreign['count'] > len(foreign['steps']) else ''
    return f"{foreign['count']} (steps {steps}{more})"


def summary_table(report: Dict) -> str:
    """A fixed-width two-column table of the main numbers of a report."""
    m = report['metrics']
    rec = report['recording']
    rows = [('recording', rec['path']),
            ('complete (finished by the recorder)', rec['complete']),
            ('messages / duration [s]', f"{rec['message_count']} / {rec['duration_s']:.3f}")]
    rows += [(f'  {name}', f"{t['count']}  [{t['type']}]")
             for name, t in sorted(rec['topics'].items())]
    tr = m['tracking']
    rows += [('tracked outputs', tr['tracked_outputs']),
             ('tracking samples', tr['samples']),
             ('tracking cost (sum of squared errors)', tr['cost']),
             ('tracking RMSE (all tracked)', tr['rmse'])]
    rows += [(f'  RMSE y[{i}]', v['rmse']) for i, v in tr['per_output'].items()]
    rows += [(f"  config version {s['config_version']}",
              f"RMSE {_fmt(s['tracking']['rmse'])}, {_ranges(s['ranges'])}")
             for s in m.get('tracking_segments', ())]
    bounds = m['input_bounds']
    rows += [('input-bound violations', bounds['violations'] if bounds else None),
             ('saturated samples', m['saturated_samples']),
             ('diverged samples', m['diverged_samples']),
             ('missed ticks / considered', f"{m['ticks']['missed']} / "
                                           f"{m['ticks']['considered']}"),
             ('foreign inputs (u not from the controller)', _foreign(m['foreign_inputs'])),
             ('fallbacks / terminal fallbacks', f"{m['fallbacks']} / "
                                                f"{m['terminal_fallbacks']}")]
    st = m['solve_time']
    rows += [('solve time p50 / p99 / max [ms]',
              ' / '.join(_fmt(None if v is None else 1e3 * v)
                         for v in (st['p50'], st['p99'], st['max']))),
             ('model versions published', m['model_versions']['published'])]
    rows += [(f"training {t['job']} {t['method']}"
              + (f" {t['phase']}" if t['phase'] != t['job'] else ''),
              f"iteration {t['iteration']}/{t['total']}, loss {_fmt(t['final_loss'])}")
             for t in m['training']]
    rows += [(f"parameters of {c['node']} at {c['stamp']:.3f} s",
              ', '.join(f'{k}={v}' for k, v in c['parameters'].items()))
             for c in m.get('parameter_changes', ())]
    rows += [('plots', ', '.join(report['plots']) or '-')]
    width = max(len(name) for name, _ in rows)
    return '\n'.join(f'{name:<{width}}  {_fmt(value)}' for name, value in rows)

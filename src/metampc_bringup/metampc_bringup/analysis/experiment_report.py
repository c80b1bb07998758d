"""The experiment's results from its recordings alone: per-seed reports, the paper's figures
and the table of its claims.

:func:`seed_report` cuts each tracking run of a seed's recording out by its header stamps,
using the orchestrator's events (:mod:`metampc_bringup.experiment_events`), computes its
metrics (:func:`metampc_bringup.analysis.metrics.compute_metrics`) and plots it;
:func:`heldout_losses` scores each published model with l_SSM of eq. (SSM) on fresh samples of
theta*; :func:`experiment_report` gathers the seeds into ``report.json``, ``report.md`` and
the figures (the paper's Figs. 2 and 3, tracking), with claims (a)-(c) counted over seeds and
each pairwise claim tested by :mod:`metampc_bringup.analysis.paired_stats` (:func:`pairwise`).
In: an experiment's output folder; out: files in it. The claims and how to read the report:
docs/experiments.md. No rclpy here.
"""
import json
import math
import os
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import matplotlib
import numpy as np

from metampc_bringup.analysis.metrics import compute_metrics
from metampc_bringup.analysis.paired_stats import claim_cells, paired_claim
from metampc_bringup.analysis.plots import signal_labels
from metampc_bringup.analysis.run_report import json_safe
from metampc_bringup.analysis.run_series import RunSeries, SeriesBuilder
from metampc_bringup.experiment_config import (from_mapping, learner_config, learner_method,
                                               NARX_PREFIX)
from metampc_bringup.experiment_events import (Adapted, BufferingStopped, CollectEnd, Done,
                                               ExperimentEvent, MetaTrained, read_events, Start,
                                               TrackEnd, TrackStart)
from metampc_learner.heldout import (HELDOUT_STREAM, heldout_seed, model_heldout_loss,
                                     plant_source, target_heldout)
from metampc_learner.meta_train import META_METHODS
from metampc_model.weights_codec import (DecodedNarx, DecodedWeights, fields_of,
                                         model_from_fields)
from metampc_recording.recording_reader import read_recording

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)

K_STEPS = (0, 1, 5, 20)
STAMP_TOL = 1e-6    # s; stamps are n * dt, exact to float rounding
PLANT_OUTPUT = 'metampc_msgs/msg/PlantOutput'
CLOSED_LOOP = (PLANT_OUTPUT, 'metampc_msgs/msg/ControlInput',
               'metampc_msgs/msg/MpcStatus')
NSSM_WEIGHTS = 'metampc_msgs/msg/NssmWeights'
PLANT_INFO = 'metampc_msgs/msg/PlantInfo'


def tracking_spans(events: List[ExperimentEvent]) -> Dict[str, Tuple[float, float, int]]:
    """Per method: the sim-time span [start, end] (s) of its finished tracking run and the
    model version its controller ran (0 for nmpc)."""
    starts = {e.method: e for e in events if isinstance(e, TrackStart)}
    return {e.method: (starts[e.method].stamp, e.stamp, int(starts[e.method].model_version))
            for e in events if isinstance(e, TrackEnd) and e.method in starts}


def tracking_series(recording, spans: Dict[str, Tuple[float, float, int]]
                    ) -> Dict[str, RunSeries]:
    """Per method, the series of the closed-loop messages stamped within its span: outputs
    y_0..y_n, and the inputs and statuses answering steps 0..n-1 with the run's model version
    only. The answer to y_n comes or not depending on when the controller was deactivated, and
    an inactive controller that is activated next may still answer the previous run's y_n
    with its new model; neither belongs to the run.

    ``plant_info`` (latched, the last one recorded) is added to every series for the bounds.
    """
    builders = {method: SeriesBuilder() for method in spans}
    wanted = [t.name for t in recording.topics.values()
              if t.type_name in CLOSED_LOOP or t.type_name == 'metampc_msgs/msg/PlantInfo']
    for topic, raw, msg in recording.decoded(wanted):
        if topic.type_name not in CLOSED_LOOP:
            for builder in builders.values():
                builder.add(topic.type_name, msg, raw.log_time)
            continue
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        answer = topic.type_name != PLANT_OUTPUT    # stamped with the y it answers
        for method, (start, end, version) in spans.items():
            last = end - STAMP_TOL if answer else end + STAMP_TOL
            if start - STAMP_TOL <= stamp <= last and getattr(
                    msg, 'model_version', version) == version:
                builders[method].add(topic.type_name, msg, raw.log_time)
    return {method: builder.build() for method, builder in builders.items()}


def _messages(recording, type_name: str) -> List[Any]:
    """The decoded messages of every topic of `type_name`, in log-time order."""
    topics = [t.name for t in recording.topics.values() if t.type_name == type_name]
    return [msg for _, _, msg in recording.decoded(topics)]


def published_models(recording) -> Dict[int, Union[DecodedWeights, DecodedNarx]]:
    """Every model the learner published (NssmWeights messages, NSSMs or feature NARXs),
    decoded, by version."""
    return {int(msg.version): model_from_fields(fields_of(msg))
            for msg in _messages(recording, NSSM_WEIGHTS)}


def heldout_losses(recording, events: List[ExperimentEvent], config: Dict[str, Any]
                   ) -> Tuple[Dict[str, Any], Dict[str, Dict[str, Any]]]:
    """The seed's held-out target set and the l_SSM of each published model on it.

    The set (``metampc_learner.heldout.target_heldout``): fresh bounded excitation episodes
    of theta* (the start event's), with the source settings the learner had in this run
    (rebuilt from the run config) at the dt, substeps, input bounds and state box of the last
    recorded plant_info, seeded by ``heldout_seed(seed)``. Each model is scored in its own
    normalisation on windows of H + T samples (T: the learner's loss_horizon parameter; a feature
    NARX's: the same windows' last p + T, T its narx_horizon).

    Returns:
        (the set: samples, episodes, seed, stream, elapsed_s (wall time of decoding,
        simulating and scoring); per method: {'samples', 'meta', 'adapted'}, the l_SSM
        (normalised units) of the model of its meta_train and of its adapt event, None
        without one, e.g. the meta stage of supervised and oracle).
    """
    t0 = time.monotonic()
    start = next(e for e in events if isinstance(e, Start))
    seed = int(start.seed)
    learner = learner_config(from_mapping(config['experiment']), seed)
    source = learner.source
    plants = _messages(recording, PLANT_INFO)
    if plants:
        p = plants[-1]
        source = plant_source(source, p.dt, p.substeps, p.u_min, p.u_max, p.state_bound)
    trajectories = target_heldout(np.atleast_1d(start.theta), source, seed)
    samples = sum(len(t) for t in trajectories)
    models = published_models(recording)
    losses: Dict[str, Dict[str, Any]] = {}
    for e in events:
        if not isinstance(e, (MetaTrained, Adapted)):
            continue
        weights = models.get(int(e.model_version))
        entry = losses.setdefault(e.method, {'samples': samples, 'meta': None,
                                             'adapted': None})
        entry['meta' if isinstance(e, MetaTrained) else 'adapted'] = (
            None if weights is None
            else model_heldout_loss(weights, trajectories,
                                    learner.narx_meta.horizon if isinstance(weights, DecodedNarx)
                                    else learner.nssm.loss_horizon, learner.nssm.history))
    about = {'samples': samples, 'episodes': len(trajectories), 'seed': heldout_seed(seed),
             'stream': HELDOUT_STREAM, 'elapsed_s': time.monotonic() - t0}
    return about, losses


def seed_report(path: str, out_dir: Optional[str] = None, plots: bool = True) -> Dict[str, Any]:
    """Report of one seed's recording (`path`: MCAP file or its folder); writes
    ``report.json`` and ``tracking_<method>.png`` into `out_dir` (default: the folder).
    The held-out target set is in ``heldout``, each method's losses on it in
    ``methods.<method>.heldout`` (:func:`heldout_losses`)."""
    recording = read_recording(path)
    out_dir = out_dir or os.path.dirname(os.path.abspath(recording.path))
    events = read_events(recording)
    start = next((e for e in events if isinstance(e, Start)), None)
    if start is None:
        raise ValueError(f'{recording.path} holds no experiment events (not an experiment '
                         'recording?); use scripts/replay.py for a plain run')
    config = recording.run_config()
    tracked = [int(i) for i in config.get('tracked_outputs', [0])]
    ends = {e.method: e for e in events if isinstance(e, TrackEnd)}
    methods: Dict[str, Dict[str, Any]] = {}
    for method, series in tracking_series(recording, tracking_spans(events)).items():
        metrics = compute_metrics(series, tracked)
        metrics['escaped'] = bool(ends[method].diverged)
        metrics['steps'] = int(ends[method].steps)
        if plots:
            metrics['plot'] = plot_tracking({method: series}, tracked,
                                            os.path.join(out_dir, f'tracking_{method}.png'))
        methods[method] = {'tracking': metrics}
    for e in events:
        if isinstance(e, (MetaTrained, Adapted)):
            methods.setdefault(e.method, {})[e.KIND] = {
                k: v for k, v in e.record().items() if k not in ('event', 'method')}
    heldout, losses = heldout_losses(recording, events, config)
    for method, entry in losses.items():
        methods[method]['heldout'] = entry
    done = next((e for e in events if isinstance(e, Done)), None)
    report = json_safe({
        'recording': os.path.abspath(recording.path),
        'complete': recording.complete and done is not None,
        'seed': start.seed, 'theta': start.theta, 'methods_compared': start.methods,
        'collect': _record(events, CollectEnd),
        'buffering': _record(events, BufferingStopped),
        'timings': done.timings if done else None,
        'heldout': heldout,
        'methods': methods,
        'config': config.get('experiment', {}),
    })
    with open(os.path.join(out_dir, 'report.json'), 'w') as f:
        json.dump(report, f, indent=2, sort_keys=True)
    return report


def _record(events: List[ExperimentEvent], kind: type) -> Optional[Dict[str, Any]]:
    """The first event of `kind` as recorded (its JSON object), None without one."""
    return next((e.record() for e in events if isinstance(e, kind)), None)


# --- figures ---------------------------------------------------------------------------------

def _curves(reports: List[Dict], method: str, kind: str) -> List[np.ndarray]:
    curves = []
    for report in reports:
        entry = report['methods'].get(method, {}).get(kind)
        if entry and entry.get('loss_curve'):
            curves.append(np.array([np.nan if v is None else v for v in entry['loss_curve']]))
    return curves


def _band(ax, curves: List[np.ndarray], x0: int, label: str) -> bool:
    if not curves:
        return False
    n = min(len(c) for c in curves)
    stack = np.stack([c[:n] for c in curves])
    x = np.arange(x0, x0 + n)
    line, = ax.plot(x, np.nanmedian(stack, axis=0), label=f'{label} (median of {len(curves)})')
    if len(curves) > 1:
        ax.fill_between(x, np.nanmin(stack, axis=0), np.nanmax(stack, axis=0),
                        color=line.get_color(), alpha=0.2)
    return True


def plot_loss_figure(reports: List[Dict], methods: Sequence[str], kind: str, path: str,
                     title: str, xlabel: str) -> Optional[str]:
    """Median (and min-max band) over seeds of the `kind` ('meta_train'|'adapt') loss curves."""
    fig, ax = plt.subplots(figsize=(7, 4.2))
    drawn = [_band(ax, _curves(reports, m, kind), 1 if kind == 'meta_train' else 0, m)
             for m in methods]
    if not any(drawn):
        plt.close(fig)
        return None
    ax.set_yscale('log')
    ax.set_xlabel(xlabel)
    ax.set_ylabel('loss (normalised units)')
    ax.set_title(title)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_tracking(series: Dict[str, RunSeries], tracked: Sequence[int], path: str) -> str:
    """Tracked outputs of each method's run and the reference, then each input, against
    time since reset; one panel each, named with units as plant_info gives them.

    The widest-swinging run is drawn first, so that a method that lost the plant (supervised,
    usually) lies behind the others instead of hiding them; the legend sits outside the axes.
    """
    first = next(iter(series.values()))
    n_u = first.inputs.u.shape[1] if first.inputs.u.ndim == 2 else 1
    rows = len(tracked) + n_u
    fig, axes = plt.subplots(rows, 1, figsize=(9, 2.6 * rows), sharex=True, squeeze=False)
    reference_drawn = False

    def spread(item) -> float:
        y = item[1].outputs.y
        return float(np.abs(y[:, list(tracked)]).max()) if y.size else 0.0

    for method, s in sorted(series.items(), key=spread, reverse=True):
        if not s.outputs.step.size:
            continue
        dt = s.plant_info['dt'] if s.plant_info else 1.0
        t = s.outputs.step * dt
        for row, i in enumerate(tracked):
            axes[row, 0].plot(t, s.outputs.y[:, i], label=method)
        if not reference_drawn and s.status.step.size:
            for row, i in enumerate(tracked):
                axes[row, 0].step((s.status.step + 1) * dt, s.status.y_ref0[:, i], 'k--',
                                  where='post', label='reference')
            reference_drawn = True
        for j in range(n_u):
            axes[len(tracked) + j, 0].step(s.inputs.step * dt, s.inputs.u[:, j], where='post',
                                           label=method)
    outputs = signal_labels(first, 'output', first.n_y)
    labels = [outputs[i] for i in tracked] + signal_labels(first, 'input', n_u)
    for row, ax in enumerate(axes[:, 0]):
        ax.set_ylabel(labels[row])
        ax.grid(alpha=0.3)
        if row < len(tracked):
            ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize='small')
    axes[-1, 0].set_xlabel('time since reset, s')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return os.path.basename(path)


# --- claims ----------------------------------------------------------------------------------

def _adapt_loss(report: Dict, method: str, k: int) -> float:
    curve = report['methods'].get(method, {}).get('adapt', {}).get('loss_curve') or []
    value = curve[k] if k < len(curve) else None
    return math.nan if value is None else float(value)


def _tracking_cost(report: Dict, method: str) -> float:
    tracking = report['methods'].get(method, {}).get('tracking')
    if not tracking or tracking['escaped']:
        return math.inf if tracking else math.nan
    return float(tracking['tracking']['cost'])


# Claim (b): the held-out target losses in this order.
B_ORDER = ('imaml', 'maml', 'supervised')
# Pairwise claims 'a < b' with statistics; the chain of (b) is the first two; (a) the first.
ADAPT_PAIRS = (('imaml', 'maml'), ('maml', 'supervised'), ('imaml', 'supervised'))
# The yardsticks (true model, target's own data): compared 'vs', no curve in Fig. 3.
REFERENCES = ('nmpc', 'oracle', NARX_PREFIX + 'oracle')
# The linear ARX baseline (learner method 'arx'): the yardstick of the meta-learned models.
ARX_PAIRS = (('imaml', 'arx'), ('maml', 'arx'))
# The feature NARX's (experiment methods narx_*) against the ARX of its class (the same
# least-squares ARX(p), scored on the same windows), and in tracking against the NSSM's.
NARX_ARX_PAIRS = tuple((NARX_PREFIX + a, NARX_PREFIX + b) for a, b in ARX_PAIRS)
NARX_TRACKING_PAIRS = (*NARX_ARX_PAIRS, *((NARX_PREFIX + a, b) for a, b in ARX_PAIRS),
                       *((NARX_PREFIX + a, a) for a, _ in ARX_PAIRS),
                       *((NARX_PREFIX + a, 'nmpc') for a, _ in ARX_PAIRS))
TRACKING_PAIRS = (('imaml', 'maml'), ('imaml', 'supervised'), ('maml', 'supervised'),
                  ('imaml', 'nmpc'), ('imaml', 'oracle'), ('maml', 'nmpc'), ('maml', 'oracle'),
                  *ARX_PAIRS, *NARX_TRACKING_PAIRS)
NAMES = {'imaml': 'iMAML', 'maml': 'MAML', 'nmpc': 'NMPC', 'arx': 'ARX'}
NAMES.update({NARX_PREFIX + m: f'NARX {NAMES.get(m, m)}'
              for m in ('imaml', 'maml', 'arx', 'oracle')})


def pairwise(values_per_seed: List[Dict[str, float]], pairs: Sequence[Tuple[str, str]]
             ) -> Dict[str, Dict[str, Any]]:
    """Per claim 'a < b' of `pairs`, keyed ``'a<b'``: :func:`paired_claim` of the per-seed
    values (NaN or no key = missing) as log ratios a/b, losses and costs spanning orders of
    magnitude over seeds. Pairs with a method that has no value on any seed (not in the run)
    are left out."""
    def column(method: str) -> List[float]:
        return [v.get(method, math.nan) for v in values_per_seed]

    return {f'{a}<{b}': paired_claim(column(a), column(b), log=True) for a, b in pairs
            if not (np.all(np.isnan(column(a))) or np.all(np.isnan(column(b))))}


def claims(reports: List[Dict]) -> Dict[str, Any]:
    """The paper's claims (a)-(c), each as per-seed values and the count of seeds where it
    holds (a comparison with a missing value counts as not holding), and ``stats``, the
    statistics of each pairwise claim (:func:`pairwise`): in (a) and in (b) per K, and
    ``c_tracking_cost_stats`` for the tracking costs (an escaped run costs inf)."""
    out: Dict[str, Any] = {'seeds': len(reports)}
    final = [(_final(r, 'imaml'), _final(r, 'maml')) for r in reports]
    out['a_meta_loss_imaml_below_maml'] = {
        'final_losses': final, 'holds': sum(1 for i, m in final if i < m),
        'stats': pairwise([{'imaml': i, 'maml': m} for i, m in final], ADAPT_PAIRS[:1])}
    b = {}
    for k in K_STEPS:
        values = [{m: _adapt_loss(r, m, k) for m in B_ORDER}
                  for r in reports]
        b[str(k)] = {'losses': values,
                     'holds': sum(1 for v in values
                                  if v['imaml'] < v['maml'] < v['supervised']),
                     'stats': pairwise(values, ADAPT_PAIRS)}
    out['b_adaptation_order'] = b
    large = {}     # the same pairs on >= 2000 independent samples: meta-model, adapted model
    for stage in ('meta', 'adapted'):
        values = [{m: _heldout(r, m, stage) for m in r['methods']} for r in reports]
        large[stage] = {'losses': values,
                        'stats': pairwise(values, ADAPT_PAIRS + ARX_PAIRS + NARX_ARX_PAIRS)}
    out['b_heldout_large'] = large
    c = {}
    present = sorted({m for r in reports for m in r['methods']})
    for method in present:
        costs = [_tracking_cost(r, method) for r in reports]
        c[method] = {
            'cost': costs,
            'vs_oracle': [x / _tracking_cost(r, 'oracle') for x, r in zip(costs, reports)],
            'vs_nmpc': [x / _tracking_cost(r, 'nmpc') for x, r in zip(costs, reports)],
            'escaped': sum(1 for r in reports
                           if r['methods'].get(method, {}).get('tracking', {}).get('escaped')),
            'fallbacks': [r['seed'] for r in reports       # the learner's gain check
                          if r['methods'].get(method, {}).get('adapt', {}).get('fallback')]}
    out['c_tracking_cost'] = c
    out['c_tracking_cost_stats'] = pairwise(
        [{m: _tracking_cost(r, m) for m in present} for r in reports], TRACKING_PAIRS)
    return out


def _heldout(report: Dict, method: str, stage: str) -> float:
    """l_SSM of the method's `stage` ('meta' | 'adapted') model on the large held-out set."""
    value = report['methods'].get(method, {}).get('heldout', {}).get(stage)
    return math.nan if value is None else float(value)


def _final(report: Dict, method: str) -> float:
    value = report['methods'].get(method, {}).get('meta_train', {}).get('final_loss')
    return math.nan if value is None else float(value)


def _fmt(x: float) -> str:
    return 'n/a' if x is None or (isinstance(x, float) and math.isnan(x)) else (
        'escaped' if x == math.inf else f'{x:.4g}')


def _median(values: Sequence[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.median(finite)) if finite else math.nan


def _claim_name(key: str) -> str:
    """'imaml<maml' as 'iMAML < MAML'; against a reference 'iMAML vs NMPC'."""
    a, b = key.split('<')
    return f"{NAMES.get(a, a)} {'vs' if b in REFERENCES else '<'} {NAMES.get(b, b)}"


def _claim_row(label: str, stats: Dict[str, Any]) -> str:
    return '| ' + ' | '.join((label, *claim_cells(stats))) + ' |'


def _heldout_section(report: Dict[str, Any]) -> List[str]:
    """report.md's held-out table: per method, the median over seeds of the l_SSM of its
    meta-model and of its adapted model on the independent target set ([] without one)."""
    seeds = [r for r in report['per_seed'] if r.get('heldout')]
    if not seeds:
        return []
    lines = ['', f"## Held-out target loss on {min(r['heldout']['samples'] for r in seeds)} "
             'independent samples', '',
             'l_SSM (normalised units) of each published model on fresh simulated episodes '
             f'of theta*, median over {len(seeds)} seed(s). The adaptation curves (Fig. 3, '
             'claim (b)) are on the samples the learner held out of D_target.', '',
             '| method | meta-model | adapted |', '|---|---|---|']
    for method in report['methods']:
        entries = [r['methods'][method]['heldout'] for r in seeds
                   if 'heldout' in r['methods'].get(method, {})]
        if entries:
            med = [_fmt(_median([math.nan if e[stage] is None else e[stage] for e in entries]))
                   for stage in ('meta', 'adapted')]
            lines.append(f'| {method} | ' + ' | '.join(med) + ' |')
    return lines


def theta_text(theta) -> str:
    """'0.029' for one component, '(0.550, 0.610)' for more."""
    values = np.atleast_1d(theta)
    text = ', '.join(f'{v:.3f}' for v in values)
    return text if values.size == 1 else f'({text})'


def markdown(report: Dict[str, Any]) -> str:
    """report.md: set-up, timings, the claims table, per-method tracking, figures."""
    cl = report['claims']
    n = cl['seeds']
    wall = report['wall_time_s']   # None: rebuilt from recordings of a folder without one
    lines = [f"# metampc experiment: {', '.join(report['methods'])}", '',
             f"Seeds: {report['seeds']} (theta* = "
             + ', '.join(theta_text(t) for t in report['thetas']) + ')', '',
             f'Wall time: {wall:.0f} s in all.' if wall is not None and math.isfinite(wall)
             else 'Wall time: not recorded (report rebuilt from the recordings).', '',
             '## Claims of the paper, as measured', '',
             "Per claim 'a < b', over the seeds with both values (an escaped run costs inf): "
             'the seeds where it holds; the median of the ratio a/b (loss or tracking cost) '
             'with its 95 % percentile-bootstrap interval (seeds resampled); the two-sided '
             'Wilcoxon signed-rank p-value of the log ratios; the verdict: supported when the '
             'interval lies below 1, contradicted when above. Against a reference (NMPC on the '
             "true model, the oracle NSSM) the ratio is the method's cost over the reference's.",
             '', '| claim | holds in | median ratio a/b [95 % CI] | Wilcoxon p | verdict |',
             '|---|---|---|---|---|']
    medians = ['', '### Median values over seeds', '', '| quantity | median |', '|---|---|']
    compared = set(report['methods'])
    a = cl['a_meta_loss_imaml_below_maml']
    if set(ADAPT_PAIRS[0]) <= compared:
        lines += [_claim_row(f'(a) final meta-training loss: {_claim_name(key)}', stats)
                  for key, stats in a['stats'].items()]
        medians.append('| (a) final meta-training loss | iMAML '
                       f"{_fmt(_median([i for i, _ in a['final_losses']]))}, MAML "
                       f"{_fmt(_median([m for _, m in a['final_losses']]))} |")
    for k, entry in cl['b_adaptation_order'].items():
        if not set(B_ORDER) <= compared:
            break
        if all(math.isnan(x) for v in entry['losses'] for x in v.values()):
            lines.append(f'| (b) held-out target loss after {k} steps | not measured '
                         '(adaptation ran fewer steps) | | | |')
            continue
        lines.append(f"| (b) held-out target loss after {k} steps: iMAML < MAML < supervised "
                     f"| {entry['holds']}/{n} | | | |")
        lines += [_claim_row(f'(b) after {k} steps: {_claim_name(key)}', stats)
                  for key, stats in entry['stats'].items()]
        medians.append(f'| (b) held-out target loss after {k} steps | ' + ', '.join(
            f"{NAMES.get(m, m)} {_fmt(_median([v[m] for v in entry['losses']]))}"
            for m in B_ORDER) + ' |')
    for stage, entry in cl.get('b_heldout_large', {}).items():
        lines += [_claim_row(f'(b) {stage} model on the large held-out set: '
                             f'{_claim_name(key)}', stats)
                  for key, stats in entry['stats'].items()]
    lines += [_claim_row(f'(c) tracking cost: {_claim_name(key)}', stats)
              for key, stats in cl['c_tracking_cost_stats'].items()]
    for method, entry in cl['c_tracking_cost'].items():
        arx_flew = (f"; the ARX flew in its place on seeds {entry['fallbacks']}"
                    if entry.get('fallbacks') else '')
        medians.append(f'| (c) tracking cost of {NAMES.get(method, method)} (escaped '
                       f"{entry['escaped']}/{n}{arx_flew}) | {_fmt(_median(entry['cost']))}; "
                       f"vs oracle {_fmt(_median(entry['vs_oracle']))}, "
                       f"vs NMPC {_fmt(_median(entry['vs_nmpc']))} |")
    lines += medians
    lines += ['', '## Tracking (RMSE of the tracked outputs, per seed)', '',
              '| method | ' + ' | '.join(f'seed {s}' for s in report['seeds']) + ' |',
              '|---|' + '---|' * len(report['seeds'])]
    for method in report['methods']:
        row = []
        for r in report['per_seed']:
            t = r['methods'].get(method, {}).get('tracking')
            row.append('n/a' if not t else
                       'escaped' if t['escaped'] else _fmt(t['tracking']['rmse']))
        lines.append(f'| {method} | ' + ' | '.join(row) + ' |')
    lines += _heldout_section(report)
    lines += ['', '## Figures', '']
    lines += [f'![{name}]({name})' for name in report['figures']]
    lines += ['', '## Hyperparameters', '', '```json',
              json.dumps({k: report['config'][k] for k in ('meta_train', 'adapt', 'learner',
                                                           'controller')}, indent=2),
              '```', '']
    return '\n'.join(lines)


def experiment_report(seed_reports: List[Dict], out_dir: str, config: Dict[str, Any],
                      wall_time_s: float) -> Dict[str, Any]:
    """Gather per-seed reports into `out_dir`: report.json, report.md and the figures."""
    methods = list(config['methods'])
    figures = []
    meta = [m for m in methods if learner_method(m)[0] in META_METHODS]
    fig2 = plot_loss_figure(seed_reports, meta, 'meta_train',
                            os.path.join(out_dir, 'fig2_meta_training.png'),
                            'Meta-training loss (Fig. 2)', 'outer step')
    fig3 = plot_loss_figure(seed_reports, [m for m in methods if m not in REFERENCES],
                            'adapt',
                            os.path.join(out_dir, 'fig3_adaptation.png'),
                            'Held-out target loss during adaptation (Fig. 3)',
                            'adaptation step')
    figures += [os.path.basename(p) for p in (fig2, fig3) if p]
    recording = read_recording(seed_reports[0]['recording'])
    spans = tracking_spans(read_events(recording))
    if spans:
        tracked = [int(i) for i in config.get('tracked_outputs', [0])]
        figures.append(plot_tracking(tracking_series(recording, spans), tracked,
                                     os.path.join(out_dir, 'tracking_all_methods.png')))
    report = json_safe({
        'methods': methods, 'seeds': [r['seed'] for r in seed_reports],
        'thetas': [r['theta'] for r in seed_reports], 'wall_time_s': wall_time_s,
        'claims': claims(seed_reports), 'figures': figures, 'config': config,
        'per_seed': seed_reports})
    with open(os.path.join(out_dir, 'report.json'), 'w') as f:
        json.dump(report, f, indent=2, sort_keys=True)
    with open(os.path.join(out_dir, 'report.md'), 'w') as f:
        f.write(markdown(_restore(report)))
    return report


def _restore(report: Dict) -> Dict:
    """JSON-safe report back to floats (None -> nan) for formatting."""
    def fix(v):
        if v is None:
            return math.nan
        if isinstance(v, dict):
            return {k: fix(x) for k, x in v.items()}
        if isinstance(v, list):
            return [fix(x) for x in v]
        return v
    return {**report, 'claims': fix(report['claims'])}

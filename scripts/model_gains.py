#!/usr/bin/env python3
"""Per seed and method of a run folder: the adapted NSSM's steady-state gain and slowest pole
against the target plant's, and its N-step prediction as the MPC plans with it on the NMPC's
closed loop (metampc_bringup.analysis.model_gains; docs/mpc.md).

Printed per seed and method: tracking cost / NMPC; the slowest pole's time constant (s) of
the model and of the plant linearised at u0; eig(G_p G_m^+) (1: the model's gain is right,
small: too large, negative: wrong sign); E as planned (offset-free by the run's form and gain,
``model_check.check``) over the NMPC's tracking run of the seed, and E of persistence there;
where the run flew the ``arx`` method, eig(G_arx G_m^+) on the tracked outputs (the gain the
least-squares fit of the same samples gives, against the model's: negative, the model's sign
disagrees with its own data's; '-' without an ARX).

    python scripts/model_gains.py RUN [--nmpc-run RUN2] [--u0 3.0,3.0]

``--nmpc-run``: take the NMPC (its cost and its loop) from another run of the same seeds and
configuration (a run made with ``--methods imaml,maml``). ``--u0``: the input of the
linearisation (default: the experiment's first reference input, else the middle of the input
bounds). A run folder without a report or a seed without an NMPC run is one error line, exit 2;
a plant (or model) without a steady state at u0 prints n/a in the plant's columns and the
reason on stderr.
"""
import argparse
import json
import os
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('run', help='a run folder of scripts/run_experiment.py')
    parser.add_argument('--nmpc-run', help='the run folder holding the NMPC of the same seeds')
    parser.add_argument('--u0', help='input of the linearisation, comma-separated')
    args = parser.parse_args(argv)
    from dataclasses import replace
    import numpy as np
    from metampc_bringup.analysis.experiment_report import tracking_series, tracking_spans
    from metampc_bringup.analysis.model_gains import compare, time_constant
    from metampc_bringup.analysis.retrack import adapted_models, seed_recordings
    from metampc_bringup.experiment_events import read_events
    from metampc_bringup.analysis.retrack import controller_settings
    from metampc_controller.model_check import check
    from metampc_model.predictor import NssmPredictor
    from metampc_model.steady_gain import agreement, steady_gain
    from metampc_model.weights_codec import fields_of, weights_from_fields
    from metampc_plant.registry import get_family
    from metampc_recording.recording_reader import read_recording

    def text(eigs):
        return ' '.join(f'{v.real:+.2f}' + (f'{v.imag:+.2f}j' if abs(v.imag) > 1e-9 else '')
                        for v in eigs)

    def report_of(run):
        try:
            with open(os.path.join(run, 'report.json')) as f:
                return json.load(f)
        except (OSError, ValueError) as err:
            parser.error(f'{run}: no readable report.json ({err})')

    report = report_of(args.run)
    nmpc_run = args.nmpc_run or args.run
    nmpc_report = report_of(nmpc_run)
    nmpc = {int(p['seed']): p['methods'].get('nmpc') for p in nmpc_report['per_seed']}
    nmpc_recordings = seed_recordings(nmpc_run)
    recordings = seed_recordings(args.run)
    print('seed | method | cost / NMPC | slowest pole: model / plant (s) | eig(G_p G_m^+) | '
          'E as planned on the NMPC loop (persistence) | eig(G_arx G_m^+), tracked')
    for per in report['per_seed']:
        seed, cfg = int(per['seed']), per['config']
        if not nmpc.get(seed) or seed not in nmpc_recordings:
            parser.error(f'seed {seed}: no NMPC run in {nmpc_run} (give --nmpc-run)')
        family = get_family(cfg['family'])
        if args.u0:
            u0 = [float(v) for v in args.u0.split(',')]
        elif cfg.get('reference_inputs'):
            u0 = cfg['reference_inputs'][0]
        else:
            u0 = list((np.asarray(cfg['u_min']) + np.asarray(cfg['u_max'])) / 2.0)
        settings = controller_settings(cfg['controller'])
        rec = read_recording(nmpc_recordings[seed])
        loop = tracking_series(rec, tracking_spans(read_events(rec)))['nmpc'].outputs
        nmpc_cost = nmpc[seed]['tracking']['tracking']['cost']
        models = {}
        for method, msg in adapted_models(recordings[seed]).items():
            if msg.model_class == 'feature_narx':      # an NSSM's latent model only
                continue
            decoded = weights_from_fields(fields_of(msg))
            models[method] = decoded, NssmPredictor(decoded.config, decoded.norm, decoded.params)
        arx = models.get('arx')
        tracked = cfg.get('tracked_outputs')
        for method, (decoded, model) in models.items():
            if method not in per['methods']:
                continue
            try:
                gains = compare(model.latent, family, per['theta'], u0, cfg['dt'])
                plant = (f'{time_constant(gains.model_pole, cfg["dt"]):.0f} / '
                         f'{time_constant(gains.plant_pole, cfg["dt"]):.0f} | '
                         f'{text(gains.ratio_eigs)}')
            except ValueError as err:     # no steady state of the plant at u0 (or the model)
                plant = 'n/a | n/a'
                print(f'seed {seed}, {method}: {err}', file=sys.stderr)
            scored = len(loop.y) - decoded.config.history - 50
            verdict = check(model, None, loop.u_applied, loop.y, settings.mpc,
                            replace(settings.model_check, model_check_as_planned=True), scored)
            cost = per['methods'][method]['tracking']['tracking']['cost'] / nmpc_cost
            by_arx = '-' if arx is None else text(agreement(
                steady_gain(arx[1].latent), steady_gain(model.latent), tracked))
            print(f'{seed} | {method} | {cost:.2f} | {plant} | '
                  f'{verdict.candidate:.4f} ({verdict.reference:.4f}) | {by_arx}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())

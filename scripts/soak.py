#!/usr/bin/env python3
"""Real-time soak: a realtime plant and the latent-MPC controller for a long run; one JSON line.

The set-up is :mod:`metampc_bringup.soak.realtime_soak`, the measures those of
:mod:`metampc_bringup.soak.soak_metrics`; both, and the measured soaks, in docs/faults.md.
Reported (after a warm-up that is left out): deadline misses, controller tick and solve time
and the response time seen by the observer (ms percentiles), dropped messages, the nodes' own
stop-line counters, RSS and CPU share of the plant and the controller, the load average at
start and end. soak.png and the node logs go to --out.

Goals (issue 10): deadline misses <= 0.1 % and memory growth <= 5 % at 100 Hz for 10 minutes.

    python scripts/soak.py                           # 100 Hz for 10 minutes
    python scripts/soak.py --duration 60 --out /tmp/soak1
    python scripts/soak.py --rate 50 --weights runs/x/ckpt/adapted_imaml_v5.pt --dt 0.1
    # adaptation in the loop at 20 Hz under a theta step (docs/adaptation.md)
    python scripts/soak.py --rate 20 --dt 0.1 --duration 120 --warmup 10 \
        --weights-from runs/drift/seed_0/recording.mcap --theta 0.5 \
        --theta-schedule 60,60,-0.5 --adaptation periodic --adapt-period 5

The controller's timer runs at --controller-rate (default twice --rate); at the plant's own
rate every answer can come late (try ``--controller-rate 100``).
"""
import argparse
import json
import os
import sys
import tempfile

from metampc_bringup.soak.realtime_soak import soak, SoakConfig


def parse_args(argv=None) -> SoakConfig:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--rate', type=float, default=100.0, help='plant rate, Hz')
    parser.add_argument('--duration', type=float, default=600.0, help='measured time, s')
    parser.add_argument('--warmup', type=float, default=30.0,
                        help='s left out at the start (start-up, first model)')
    parser.add_argument('--controller-rate', type=float,
                        help='controller timer rate, Hz (default: 2 x --rate)')
    parser.add_argument('--dt', type=float,
                        help='plant sample time, s (default: 1/rate: real time)')
    parser.add_argument('--weights', help='checkpoint to control with (default: the '
                                          'hand-built linearised model)')
    parser.add_argument('--weights-from', metavar='RECORDING',
                        help="a run's recording: its last iMAML meta-model is written to "
                             '--out/meta.pt and used as --weights')
    parser.add_argument('--theta', type=float, default=0.5, help='plant damping')
    parser.add_argument('--theta-schedule', type=numbers, default=(),
                        help="the plant's theta over time: rows t_start,t_end,theta,... "
                             '(s of plant time; docs/plant.md)')
    parser.add_argument('--adaptation', default='off',
                        help='off, periodic or triggered: a learner adapts at the '
                             "controller's requests (needs --weights; docs/adaptation.md)")
    parser.add_argument('--adapt-period', type=float, default=10.0,
                        help='periodic: plant time between requests, s')
    parser.add_argument('--horizon', type=int, default=20, help='MPC horizon N')
    parser.add_argument('--seed', type=int, default=0, help='measurement noise seed')
    parser.add_argument('--out', help='folder for logs and soak.png (default: a new temp dir)')
    args = vars(parser.parse_args(argv))
    source = args.pop('weights_from')
    args['out'] = args['out'] or tempfile.mkdtemp(prefix='metampc-soak-')
    if source:
        try:
            args['weights'] = meta_model_from(source, args['out'])
        except (OSError, ValueError) as err:
            parser.error(f'--weights-from {source}: {err}')
    cfg = SoakConfig(**args)
    try:
        cfg.validate()
    except ValueError as err:
        parser.error(str(err))
    return cfg


def numbers(text: str):
    """'30,30,-0.5' -> (30.0, 30.0, -0.5)."""
    return tuple(float(v) for v in text.split(',')) if text else ()


def meta_model_from(recording: str, out: str) -> str:
    """Write the last iMAML meta-model of a recording to out/meta.pt; its path."""
    from metampc_bringup.analysis.experiment_report import NSSM_WEIGHTS
    from metampc_recording.recording_reader import read_recording
    from metampc_bringup.soak.weights_messages import save_weights
    rec = read_recording(recording)
    topics = [t.name for t in rec.topics.values() if t.type_name == NSSM_WEIGHTS]
    metas = [m for _, _, m in rec.decoded(topics) if m.stage == 'meta' and m.method == 'imaml']
    if not metas:
        raise ValueError('no iMAML meta-model in it')
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, 'meta.pt')
    save_weights(metas[-1], path)
    return path


def main(argv=None) -> int:
    cfg = parse_args(argv)
    try:
        report = soak(cfg)
    except KeyboardInterrupt:
        print(f'soak: interrupted; nodes stopped, logs in {cfg.out}', file=sys.stderr)
        return 130
    except RuntimeError as err:
        print(f'soak: {err}', file=sys.stderr)
        return 1
    print(json.dumps(report))
    return 0


if __name__ == '__main__':
    sys.exit(main())

#!/usr/bin/env python3
"""Analyse a recorded run, or play it back onto ROS topics.

    python scripts/replay.py RUN_DIR_OR_MCAP            # summary table, report.json, PNG plots
    python scripts/replay.py RUN_DIR_OR_MCAP --play [--rate 2] [--delay 1] [--wait-subscribers 10]

The analysis needs only the recording (metampc_bringup.analysis.run_report); --play needs ROS
(metampc_recording.player) and the message packages of the recorded types.
"""
import argparse
import json
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('path', help='an MCAP file, or a run folder holding one')
    parser.add_argument('--out', help='folder for report.json and plots (default: the '
                        "recording's folder)")
    parser.add_argument('--tracked', type=int, nargs='+',
                        help='output indices that track a reference (default: the run '
                        "config's tracked_outputs, else the outputs the controller "
                        'weights (q > 0 in mpc_status), else all)')
    parser.add_argument('--no-plots', action='store_true', help='skip the PNG plots')
    parser.add_argument('--json', action='store_true', help='print the report as JSON')
    parser.add_argument('--play', action='store_true',
                        help='republish the recording on its topics instead of analysing it')
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor')
    parser.add_argument('--delay', type=float, default=0.0,
                        help='seconds between creating publishers and the first message')
    parser.add_argument('--wait-subscribers', type=float, default=0.0, metavar='SECONDS',
                        help='then wait up to SECONDS until every volatile topic has a '
                        'subscriber, and as long until its first message is acknowledged')
    parser.add_argument('--topics', nargs='+', default=[], help='topics to play (default all)')
    args = parser.parse_args(argv)
    try:
        if args.play:
            from metampc_recording.player import PlayConfig, run_player
            counts = run_player(args.path, PlayConfig(
                rate=args.rate, delay=args.delay, topics=args.topics,
                wait_for_subscribers=args.wait_subscribers))
            print(json.dumps({'published': counts}, sort_keys=True))
            return 0
        from metampc_bringup.analysis.run_report import analyse, summary_table
        report = analyse(args.path, out_dir=args.out, tracked=args.tracked,
                         plots=not args.no_plots)
    except (OSError, ValueError) as err:     # a missing file, a bad option: one line
        print(f'replay: error: {err}', file=sys.stderr)
        return 2
    print(json.dumps(report, indent=2, sort_keys=True) if args.json else summary_table(report))
    return 0


if __name__ == '__main__':
    sys.exit(main())

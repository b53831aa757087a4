"""``python -m hapticloud.hardware.drives {load,dbc,bench}``: bus-load table, DBC, cycle cost."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hapticloud.hardware.drives")
    sub = parser.add_subparsers(dest="command", required=True)
    load = sub.add_parser("load", help="bus load of the schedule (docs/drive-protocol.md table)")
    load.add_argument("--json", action="store_true")
    dbc = sub.add_parser("dbc", help="write the DBC of the protocol")
    dbc.add_argument("path", type=Path)
    bench = sub.add_parser("bench", help="cost of one bus cycle (socketpair and virtual)")
    bench.add_argument("--cycles", type=int, default=5000)
    bench.add_argument("--transport", choices=("socketpair", "virtual", "both"), default="both")
    bench.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)

    if args.command == "dbc":
        from .codec import dbc_text

        args.path.write_text(dbc_text())
        return 0
    if args.command == "load":
        from .config import DriveBusConfig
        from .schedule import bus_load, drive_schedule, load_table

        cfg = DriveBusConfig()
        rows = load_table(cfg)
        if args.json:
            print(json.dumps(rows, indent=2))
            return 0
        print(f"cycle {cfg.cycle_rate_hz:g} Hz ({cfg.cycle_period_s * 1e6:g} us)")
        for r in rows:
            print(
                f"{r['case']:<62} {r['frames_per_cycle']:>6} frames  "
                f"{r['busy_us_no_stuffing']:>7} - {r['busy_us_worst']:>7} us  "
                f"{r['load_pct_no_stuffing']:>6} - {r['load_pct_worst']:>6} %"
            )
        single = bus_load(
            drive_schedule(cfg),
            cycle_rate_hz=cfg.cycle_rate_hz,
            nominal_bitrate=cfg.nominal_bitrate,
            data_bitrate=cfg.data_bitrate,
        )
        for row in single.rows:
            print(f"  {row.name:<10} {row.payload_bytes:>3} B  {row.frame_s * 1e6:7.2f} us/frame")
        return 0
    from hapticloud.core.threads import settle_numerics

    from .bench import bench_codec, bench_cycle

    settle_numerics(1)
    transports = ("socketpair", "virtual") if args.transport == "both" else (args.transport,)
    result = {"codec": bench_codec()}
    for transport in transports:
        result[f"cycle_{transport}"] = bench_cycle(args.cycles, transport=transport)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"codec only (encode command + decode 6 feedback): {result['codec']}")
    for transport in transports:
        c = result[f"cycle_{transport}"]
        print(f"{transport}:")
        for key in ("master", "emulator", "total"):
            print(f"  {key:<9} {c[key]}")
        print(f"  incomplete cycles: {c['incomplete_cycles']} of {c['cycles']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

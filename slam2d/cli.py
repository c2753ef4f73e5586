"""Command line: ``slam2d run | info | convert | simulate | eval | dump-config``.

Every user mistake (bad file, bad config, bad option) ends as one line on stderr and a
non-zero exit; a traceback means a bug in slam2d.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from slam2d.errors import Slam2dError, UsageError

log = logging.getLogger("slam2d")

EXAMPLES = """examples:
  slam2d run ../shared/datasets/intel/intel.clf.bz2 --out runs/intel
  slam2d run data/sim_office.mcap --out runs/sim --odometry-only
  slam2d run ../shared/datasets/aces/aces.clf.bz2 --out runs/aces --rate 5
  slam2d info ../shared/datasets/fr079/fr079.clf.bz2 --json
  slam2d convert ../shared/datasets/aces/aces.clf.bz2 aces.mcap
  slam2d convert ../shared/datasets/aces/aces.clf.bz2 aces.bag      # ROS 1 bag; a name without suffix: ROS 2 bag
  slam2d run robot.bag --out runs/robot --scan-topic /scan           # ROS 1 bag, ROS 2 bag folder, .db3, .mcap
  slam2d run old.log.gz --out runs/old --scan-period 0.2            # a CARMEN log whose timestamps are broken
  slam2d simulate data/sim_office.mcap --seed 7
  slam2d eval relations runs/intel/trajectory.txt ../shared/datasets/intel/intel.relations
  slam2d dump-config > my.yaml
"""


CONVERT_EXAMPLES = """examples:
  slam2d convert ../shared/datasets/intel/intel.clf.bz2 intel.mcap      # MCAP (ROS 2 messages, CDR)
  slam2d convert ../shared/datasets/intel/intel.clf.bz2 intel.bag       # ROS 1 bag
  slam2d convert ../shared/datasets/intel/intel.clf.bz2 intel_ros2      # ROS 2 bag folder, MCAP storage
  slam2d convert ../shared/datasets/intel/intel.clf.bz2 intel_db3 --storage sqlite3   # ROS 2 bag, .db3
  slam2d convert robot.bag robot.mcap --scan-topic /front/scan          # a bag with two LaserScan topics
"""


def _add_input(p):
    p.add_argument("input", help="CARMEN log (.clf/.log, plain/.gz/.bz2), MCAP (.mcap), ROS 1 bag (.bag) or "
                   "ROS 2 bag (its folder, or its .db3/.mcap file)")
    p.add_argument("--scan-topic", default=None, help="ROS input: LaserScan topic (default: the only one)")
    p.add_argument("--odom-topic", default=None, help="ROS input: Odometry topic (default: the only one, if any)")
    p.add_argument("--scan-period", type=float, default=None, metavar="S",
                   help="CARMEN input whose timestamps are unusable (a 32-bit wrap, stamps going back): ignore "
                        "them and stamp the scans S seconds apart in file order")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="slam2d", description="2D LiDAR SLAM: maps and trajectories from laser logs.",
                                 epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("run", help="run SLAM on a log and write trajectory, map and summary",
                       epilog="example:\n  slam2d run ../shared/datasets/intel/intel.clf.bz2 --out runs/intel",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_input(p)
    p.add_argument("--out", required=True, help="output folder (created; files are replaced only when the run completes)")
    p.add_argument("--config", default=None, help="YAML config (default: built-in defaults = configs/default.yaml)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--odometry-only", action="store_true", help="no scan matching: poses are the wheel odometry")
    mode.add_argument("--no-loop-closure", action="store_true", help="local SLAM only (no global optimization)")
    p.add_argument("--no-odometry", action="store_true",
                   help="ignore the input's wheel odometry (predict from the recent matches' velocity)")
    p.add_argument("--max-scans", type=int, default=None, help="stop after this many scans")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--rerun", metavar="RRD", default=None, help="write a Rerun recording of the whole run to this .rrd")
    p.add_argument("--viewer", action="store_true", help="stream the run live to a spawned Rerun viewer")
    p.add_argument("--mcap", action="store_true", help="also write DIR/results.mcap (scans, poses, TF, map; ROS 2)")
    p.add_argument("--rate", type=float, default=None, metavar="R",
                   help="replay the input by its timestamps at R× real time (1 = live) and report the worst lag "
                        "behind it (summary.json: realtime)")

    p = sub.add_parser("info", help="describe a log: scans, duration, beams, ranges, odometry",
                       epilog="example:\n  slam2d info ../shared/datasets/intel/intel.clf.bz2 --json",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_input(p)
    p.add_argument("--json", action="store_true", help="machine-readable output")

    p = sub.add_parser("convert", help="convert a log to MCAP, a ROS 1 bag or a ROS 2 bag (LaserScan, Odometry, "
                       "tf_static laser mount)", epilog=CONVERT_EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_input(p)
    p.add_argument("output", help="OUT.mcap (MCAP, ROS 2 messages), OUT.bag (ROS 1 bag), or a new folder name "
                   "without suffix (ROS 2 bag: metadata.yaml + storage file)")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default=None,
                   help="ROS 2 bag storage (default mcap, the ROS 2 default since Iron; sqlite3 for Humble and older)")
    p.add_argument("--no-progress", action="store_true")

    p = sub.add_parser("simulate", help="write the deterministic simulated dataset as MCAP",
                       epilog="example:\n  slam2d simulate data/sim_office.mcap --seed 7",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("output", help="output .mcap file")
    p.add_argument("--seed", type=int, default=7, help="random seed (same seed, same bytes)")

    p = sub.add_parser("view", help="open a Rerun recording (.rrd) in the Rerun viewer",
                       epilog="example:\n  slam2d view runs/intel/run.rrd", formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("rrd", help="a recording written by slam2d run --rerun")

    p = sub.add_parser("dump-config", help="print every option with its default and description")
    p.add_argument("--config", default=None, help="print this config file's values instead of the defaults")
    p.add_argument("-o", "--output", default=None, help="write to a file instead of stdout")

    from slam2d.eval.cli import add_eval_parser

    add_eval_parser(sub)
    return ap


def _progress(total, disable, desc):
    from tqdm import tqdm

    return tqdm(total=total, disable=disable or not sys.stderr.isatty(), unit="scan", desc=desc, dynamic_ncols=True)


def _source(args):
    from slam2d.io.source import open_source

    return open_source(args.input, scan_topic=args.scan_topic, odom_topic=args.odom_topic,
                       scan_period=args.scan_period)


def _limited(source, n):
    for i, s in enumerate(source):
        if n is not None and i >= n:
            return
        yield s


def cmd_run(args) -> int:
    from slam2d.config import load_config
    from slam2d.output import OutputDir
    from slam2d.slam import Slam

    cfg = load_config(args.config)
    if args.no_odometry:
        if args.odometry_only:
            raise UsageError("--no-odometry and --odometry-only exclude each other")
        cfg.real_time_matcher.use_odometry = False
    if args.max_scans is not None and args.max_scans <= 0:
        raise UsageError("--max-scans must be positive")
    if args.rate is not None and not 1e-3 <= args.rate <= 1e6:
        raise UsageError(f"--rate must lie between 0.001 and 1e6 (times real time), not {args.rate}")
    src = _source(args)
    total = src.num_scans() if hasattr(src, "num_scans") else None
    if args.max_scans:
        total = min(total, args.max_scans) if total else args.max_scans
    OutputDir(args.out)  # a folder that cannot be written fails now, not after the run
    mode = "odometry" if args.odometry_only else "local" if args.no_loop_closure else "global"
    viz = None
    rrd_tmp = None
    if args.rerun or args.viewer:
        if args.rerun and not args.rerun.endswith(".rrd"):
            raise UsageError(f"{args.rerun}: a Rerun recording must end in .rrd")
        if args.rerun:
            writable_file(args.rerun, "Rerun recording")
        from slam2d.viz.rerun import RerunObserver

        rrd_tmp = f"{args.rerun}.partial" if args.rerun else None
        viz = RerunObserver(path=rrd_tmp, spawn=args.viewer)
    try:
        slam = Slam(cfg, mode=mode, observer=viz, source_name=args.input)
        slam.start({"input": args.input})
        pacer = None
        if args.rate is not None:
            from slam2d.pacing import Pacer

            pacer = Pacer(args.rate)
        with _progress(total, args.no_progress, "slam2d") as bar:
            for scan in _limited(src, args.max_scans):
                if pacer is not None:
                    pacer.wait(scan.timestamp)
                slam.add_scan(scan)
                if pacer is not None:
                    pacer.done()
                bar.update(1)
        result = slam.finish()
        if pacer is not None:
            result.summary["realtime"] = pacer.report()
        result.save(args.out, mcap_scans=_limited(src, args.max_scans) if args.mcap else None)
        if viz is not None:
            viz.close()
            if rrd_tmp:
                os.replace(rrd_tmp, args.rerun)
    except BaseException:
        if rrd_tmp:
            Path(rrd_tmp).unlink(missing_ok=True)
        raise
    h = result.summary["health"]
    if h["status"] != "OK":
        print(f"slam2d: warning: map health {h['status']}: " + "; ".join(h["reasons"]), file=sys.stderr)
    rt = result.summary.get("realtime")
    if rt is not None:
        print(f"realtime x{rt['rate']:g}: worst lag behind the data {rt['worst_lag_s']:.3f} s "
              f"(p99 {rt['p99_lag_s']:.3f} s, {rt['scans_late_over_1s']} scans over 1 s late)")
    wall = result.summary["wall_time_s"]
    log.info("wrote %s (%d scans, %.1f s)", args.out, len(result.stamps), wall)
    print(f"{len(result.stamps)} scans -> {args.out} in {wall:.1f} s")
    return 0


def cmd_view(args) -> int:
    p = Path(args.rrd)
    if not p.exists():
        raise UsageError(f"{p}: no such file")
    if not p.is_file():
        raise UsageError(f"{p}: is a folder, not a Rerun recording (.rrd)")
    with open(p, "rb") as f:
        head = f.read(4)
    if not head.startswith(b"RRF"):  # every .rrd the Rerun SDK writes begins so
        raise UsageError(f"{p}: not a Rerun recording (" + ("empty" if not head else "not an .rrd file") +
                         "; `slam2d run LOG --out DIR --rerun X.rrd` writes one)")
    from slam2d.viz.rerun import view

    return view(args.rrd)


def cmd_info(args) -> int:
    from slam2d.summary import describe

    source = _source(args)
    info = describe(source)
    info["file"] = args.input
    if info["has_odometry"] and info["odometry_changes_between_scans"] == 0:
        info["odometry_note"] = ("every scan's odometry reads the same pose: it carries no motion, and local SLAM "
                                 "predicts without it once the scans show the robot moving")
    facts = getattr(source, "facts", None)
    if callable(facts):  # CARMEN: what the first pass decided about no-return readings, and why
        f = facts()
        info["laser_messages"] = f.laser_messages
        info["odometry_from"] = f.odometry
        info["no_return_threshold_m"] = f.no_return_value
        if f.skipped_lasers:  # a front and a rear laser: one is read
            info["laser_messages_skipped"] = f.skipped_lasers
        info["no_return_evidence"] = f.no_return_evidence
    mount = getattr(source, "laser_mount", None)
    if mount is not None:  # ROS: where the odometry came from; whether the laser hangs upside down (mirrored)
        info["odometry_from"] = source.odometry_from
        info["laser_upside_down"] = mount.mirrored
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        for k, v in info.items():
            print(f"{k:>28}: {v}")
    return 0


def writable_file(path, what: str) -> Path:
    """``path`` as a file to be written: its folder made if missing and writable, the path itself not
    a folder; checked before any work, so a run or a conversion does not fail at its end."""
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"{p}: cannot create the folder for the {what} ({e.strerror})") from None
    if p.is_dir():
        raise UsageError(f"{p}: is a folder; the {what} is a file")
    probe = p.parent / f".{p.name}.{os.getpid()}.probe"  # write access alone says yes to root, even on /proc
    try:
        probe.open("wb").close()
        probe.unlink()
    except OSError as e:
        raise UsageError(f"{p}: cannot write the {what} there ({e.strerror})") from None
    return p


def _bag_kind(outp: Path, storage: str | None) -> str:
    """What `slam2d convert` writes to ``outp``: ``mcap_file``, ``ros1``, or a ROS 2 bag folder with
    ``sqlite3`` or ``mcap`` storage."""
    suffix = outp.suffix.lower()
    if suffix in (".mcap", ".bag"):
        if storage is not None:
            raise UsageError(f"--storage applies to a ROS 2 bag folder (an output name without suffix), not {outp}")
        return "mcap_file" if suffix == ".mcap" else "ros1"
    if suffix:
        raise UsageError(f"{outp}: output must end in .mcap or .bag, or be a new folder name (ROS 2 bag)")
    if outp.exists():
        raise UsageError(f"{outp}: exists; a ROS 2 bag is written to a new folder")
    return storage or "mcap"


def cmd_convert(args) -> int:
    import shutil

    outp = Path(args.output)
    kind = _bag_kind(outp, args.storage)
    writable_file(outp, "output")
    src = _source(args)
    total = src.num_scans() if hasattr(src, "num_scans") else None
    # written under a temporary name, renamed only when complete; a ROS 2 bag folder is built
    # inside a staging folder so that its files already carry the final name
    staging = outp.parent / f".{outp.name}.partial" if kind in ("sqlite3", "mcap") else None
    tmp = staging / outp.name if staging else Path(f"{outp}.partial")
    n = 0
    f = None
    try:
        if staging:
            shutil.rmtree(staging, ignore_errors=True)
            staging.mkdir(parents=True)
        else:
            tmp.unlink(missing_ok=True)
        if kind == "mcap_file":
            from slam2d.io.mcap import McapWriter

            f = open(tmp, "wb")
            w = McapWriter(f, source=args.input)
        else:
            from slam2d.io.rosbag import RosbagWriter

            w = RosbagWriter(tmp, kind, source=args.input)
        with _progress(total, args.no_progress, "convert") as bar:
            for scan in src:
                w.write_scan(scan)
                n += 1
                bar.update(1)
        w.finish()
        if f is not None:
            f.close()
        os.replace(tmp, outp)
    except BaseException:
        if f is not None:
            f.close()
        if staging:
            shutil.rmtree(staging, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)
        raise
    if staging:
        staging.rmdir()
    what = {"mcap_file": "MCAP", "ros1": "ROS 1 bag"}.get(kind, f"ROS 2 bag, {kind} storage")
    print(f"{n} scans -> {outp} ({what})")
    return 0


def cmd_simulate(args) -> int:
    from slam2d.io.simulator import SimConfig, write_simulation

    outp = Path(args.output)
    if outp.suffix.lower() != ".mcap":
        raise UsageError(f"{outp}: output must end in .mcap")
    writable_file(outp, "output")
    tmp = Path(f"{outp}.partial")
    try:
        n = write_simulation(tmp, SimConfig(seed=args.seed))
        os.replace(tmp, outp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    print(f"{n} scans -> {outp}")
    return 0


def cmd_dump_config(args) -> int:
    from slam2d.config import dump_config, load_config

    text = dump_config(load_config(args.config))
    if args.output:
        Path(args.output).write_text(text)
    else:
        sys.stdout.write(text)
    return 0


COMMANDS = {"run": cmd_run, "info": cmd_info, "convert": cmd_convert, "simulate": cmd_simulate,
            "dump-config": cmd_dump_config, "view": cmd_view}


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="slam2d: %(levelname)s: %(message)s")
    if args.command is None:
        ap.print_help()
        return 2
    fn = COMMANDS.get(args.command)
    if fn is None:
        from slam2d.eval.cli import run_eval

        fn = run_eval
    try:
        return fn(args)
    except Slam2dError as e:
        print(f"slam2d: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("slam2d: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 1


if __name__ == "__main__":
    sys.exit(main())

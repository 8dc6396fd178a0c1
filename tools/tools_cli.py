"""``ucr emulate`` (an emulated segment chain) and ``ucr flash`` (flash a segment over its REPL)."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    em = subparsers.add_parser(
        "emulate",
        help="run an emulated segment chain (real firmware on the MicroPython VM, pty links)",
        description="Start N emulated segments linked through pseudo-terminals; print the host "
        "port and each segment's REPL pty; run until Ctrl-C or SIGTERM. Commands on stdin "
        "(and on --control-socket) change links at run time: type 'help'.",
    )
    em.add_argument("n", nargs="?", type=int, help="number of segments (default: the robot's)")
    em.add_argument(
        "--robot", type=Path, help="U(C)RDF file: segment k is configured from its k-th bendable"
    )
    em.add_argument("--baud", type=int, help="throttle every link to this rate (bit/s)")
    em.add_argument("--latency", type=float, help="added delay on every link (s)")
    em.add_argument("--corrupt", type=float, help="byte corruption probability on every link")
    em.add_argument("--workdir", type=Path, help="keep segment directories here (default: temp)")
    em.add_argument(
        "--keep",
        action="store_true",
        help="with --workdir: reuse its existing segment directories (e.g. flashed ones) "
        "instead of repopulating them",
    )
    em.add_argument("--control-socket", type=Path, help="also accept commands on this unix socket")
    em.add_argument("--no-stdin", action="store_true", help="do not read commands from stdin")
    em.add_argument(
        "--board",
        help="run every segment as this board (esp32, esp32s3, esp32c3, …, unix): its UARTs, "
        "pins and heap; default each segment's configured board, else esp32",
    )
    em.add_argument(
        "--timing-model",
        action="store_true",
        help="the board's timing model: waits end on its RTOS tick, compute is stretched by "
        "its CPU factor (docs/emulator.md)",
    )
    em.add_argument(
        "--cpu-factor",
        type=float,
        help="with --timing-model: board/host slowdown (default measured)",
    )
    em.add_argument(
        "--source",
        action="store_true",
        help="run the firmware from source files (each segment compiles its modules at import, "
        "as after `ucr flash --source`); default: precompiled .mpy, as `ucr flash` deploys",
    )
    em.set_defaults(func=cmd_emulate)

    fl = subparsers.add_parser(
        "flash",
        help="flash a segment: firmware, protocol and its configuration from the robot file",
        description="Copy device/ firmware, protocol/ and the segment's config.json (generated "
        "from the U(C)RDF) with mpremote's raw REPL, verify every file by SHA-256 on the board, "
        "then reset it. Works on a real ESP32 and on an emulated segment's REPL pty.",
    )
    fl.add_argument("--port", required=True, help="serial port of the segment's USB REPL")
    fl.add_argument("--robot", required=True, type=Path, help="U(C)RDF file of the robot")
    fl.add_argument("--segment", required=True, help="name of the <bendable> this segment is")
    src = fl.add_mutually_exclusive_group()
    src.add_argument(
        "--mpy",
        dest="mpy",
        action="store_true",
        default=True,
        help="precompile modules with mpy-cross for the board (the default; kept for scripts)",
    )
    src.add_argument(
        "--source",
        dest="mpy",
        action="store_false",
        help="flash source files: the board compiles them at import, on its own heap (less "
        "heap left; calibration may not find room to load)",
    )
    fl.add_argument("--no-reset", action="store_true", help="do not reset the board afterwards")
    fl.add_argument(
        "--servo-driver",
        help="override the robot's servo driver (e.g. 'emulated' for an emulated segment)",
    )
    fl.add_argument(
        "--forget-calibration",
        action="store_true",
        help="remove a calibration stored on the segment (`ucr calibrate` persist): it would "
        "override the zero offsets and directions flashed from the robot file",
    )
    fl.set_defaults(func=cmd_flash)


def _error(text: str, code: int = 2) -> int:
    """One ``ucr: error:`` line; ``code``: 2 a usage error (the default), 1 a failure."""
    print(f"ucr: error: {text}", file=sys.stderr)
    return code


def _load_robot(path: Path):
    from ucrdf.errors import UcrdfError  # noqa: PLC0415 - keeps `ucr --help` fast
    from ucrdf.parser import load  # noqa: PLC0415 - keeps `ucr --help` fast

    try:
        return load(path), None
    except UcrdfError as exc:
        return None, str(exc)


def cmd_flash(args: argparse.Namespace) -> int:
    from tools.flash import FlashError, FlashInterrupted, flash  # noqa: PLC0415 - fast --help
    from tools.segment_config import (  # noqa: PLC0415 - keeps `ucr --help` fast
        SegmentConfigError,
        config_for,
        validate,
    )

    # exit codes as every ucr command's: 2 a usage error (an option value that cannot work), 1 a
    # file, a configuration or a board that cannot be flashed, 130 interrupted
    robot, err = _load_robot(args.robot)
    if robot is None:
        return _error(err or "cannot load robot", 1)
    try:
        config = config_for(robot, args.segment)
        if args.servo_driver:
            config["servo_driver"] = args.servo_driver
            err = _plan_problem(config)
            if err:
                return _error(f"--servo-driver {args.servo_driver}: {err}")
            validate(config, str(args.robot))  # e.g. PWM needs a rest pose inside each range
    except SegmentConfigError as exc:
        return _error(str(exc), 1)
    try:
        flash(
            args.port,
            config,
            mpy=args.mpy,
            reset=not args.no_reset,
            log=lambda s: print(s, flush=True),
            forget_calibration=args.forget_calibration,
        )
    except FlashInterrupted as exc:
        _error(str(exc))
        return 130  # interrupted, as every ucr command
    except FlashError as exc:
        return _error(str(exc), 1)
    except KeyboardInterrupt:
        _error("interrupted before the board was touched")
        return 130
    return 0


def _plan_problem(config: dict) -> str | None:
    """The first reason config.json's wiring cannot work on its board (protocol/boards.py)."""
    from protocol import boards  # noqa: PLC0415 - keeps `ucr --help` fast

    found = boards.problems(
        config["board"],
        config["pins"],
        config["bus"],
        config["pwm"],
        driver=config["servo_driver"],
        servo_ids=[s["id"] for s in config["servos"]],
        n=len(config["tendon_angles"]),
    )
    return f"board {config['board']!r}: {found[0][1]}" if found else None


class _Terminated(KeyboardInterrupt):
    """SIGTERM: a requested stop (a service manager, a script), unlike Ctrl-C not an interrupt."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise _Terminated


def _option_problem(args: argparse.Namespace) -> str | None:
    """An option that would be silently ignored, or out of range: why (a usage error)."""
    if args.cpu_factor is not None and not (1.0 <= args.cpu_factor < float("inf")):
        return f"--cpu-factor must be a finite number >= 1, got {args.cpu_factor}"
    if args.cpu_factor is not None and not args.timing_model:
        return (
            "--cpu-factor needs --timing-model: it scales the board's timing model; without "
            "that model the firmware runs at this computer's speed"
        )
    if args.keep and args.workdir is None:
        return (
            "--keep needs --workdir DIR: it reuses the segment directories there; without "
            "--workdir they are a new temporary directory, with nothing to keep"
        )
    return None


def _path_problem(args: argparse.Namespace) -> str | None:
    """Why --control-socket or --workdir cannot work, checked before any segment starts (the
    last check: it creates the workdir)."""
    from tools.emulator.control import socket_path_problem  # noqa: PLC0415 - keeps `ucr --help` fast

    if args.control_socket is not None:
        why = socket_path_problem(args.control_socket)
        if why:
            return f"--control-socket {why}"
    if args.workdir is not None:
        try:
            args.workdir.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            return f"--workdir {args.workdir}: exists and is not a directory"
        except OSError as exc:
            return f"--workdir {args.workdir}: cannot create it ({exc.strerror})"
        if not os.access(args.workdir, os.W_OK | os.X_OK):
            return f"--workdir {args.workdir}: not writable"
    return None


def cmd_emulate(args: argparse.Namespace) -> int:
    from tools.emulator import EmulatedChain, EmulatorError  # noqa: PLC0415 - keeps `ucr --help` fast
    from tools.emulator.control import ControlSocket, execute  # noqa: PLC0415 - keeps `ucr --help` fast
    from tools.segment_config import SegmentConfigError, configs  # noqa: PLC0415 - keeps `ucr --help` fast

    problem = _option_problem(args)
    if problem:
        return _error(problem)
    configs_list = None
    n = args.n
    if args.robot is not None:
        robot, err = _load_robot(args.robot)
        if robot is None:
            return _error(err or "cannot load robot")
        try:
            configs_list = configs(robot)
        except SegmentConfigError as exc:
            return _error(str(exc))
        for cfg in configs_list:
            cfg["servo_driver"] = "emulated"  # there are no real servos in the emulator
            if args.board is not None:  # re-wired for the emulated board: its default pins
                cfg.update(board=args.board, pins=None, bus=None, pwm=None)
        if n is None:
            n = len(configs_list)
        elif n != len(configs_list):
            return _error(
                f"{args.robot} has {len(configs_list)} bendables but {n} segments were asked for"
            )
    if n is None:
        return _error("give the number of segments or --robot")
    if not 1 <= n <= 64:
        return _error(f"number of segments must be 1..64, got {n}")
    problem = _path_problem(args)
    if problem:
        return _error(problem)
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    control = None
    rc = 0
    try:
        with EmulatedChain(
            n,
            args.workdir,
            config_for=configs_list,
            reuse_dirs=args.keep,
            board=args.board,
            timing=args.timing_model,
            cpu_factor=args.cpu_factor,
            mpy=not args.source,
        ) as chain:
            try:
                settings = {}
                if args.baud is not None:
                    settings["baud"] = args.baud
                if args.latency is not None:
                    settings["latency"] = args.latency
                if args.corrupt is not None:
                    settings["corrupt_rate"] = args.corrupt
                if settings:
                    chain.set_all_links(**settings)
            except EmulatorError as exc:
                return _error(str(exc))
            print(f"host port: {chain.host_port}")
            for k in range(n):
                print(
                    f"segment {k + 1}: REPL {chain.repl_port(k)}  uid {chain.uid(k)}  "
                    f"dir {chain.segment_dir(k)}  board {chain.board_of(k)}"
                    + (f" x{chain.cpu_factor_of(k):.0f}" if args.timing_model else "")
                )
            if args.control_socket:
                control = ControlSocket(chain, args.control_socket)
                print(f"control socket: {args.control_socket}")
            print(
                "running; Ctrl-C or SIGTERM stops it"
                + ("" if args.no_stdin else "; type 'help' for commands"),
                flush=True,
            )
            if args.no_stdin or sys.stdin is None:
                threading.Event().wait()
            else:
                for line in sys.stdin:
                    if line.strip() in ("quit", "exit"):
                        break
                    answer = execute(chain, line)
                    if answer:
                        print(answer, flush=True)
                else:
                    if sys.stdin.isatty():
                        print(
                            "stdin closed; still running (Ctrl-C or SIGTERM stops it)", flush=True
                        )
                    threading.Event().wait()  # stdin closed (background run): keep running
    except _Terminated:
        pass
    except KeyboardInterrupt:
        rc = 130  # interrupted, as every ucr command
    except EmulatorError as exc:
        return _error(str(exc))
    finally:
        if control is not None:
            control.close()
        signal.signal(signal.SIGTERM, previous)
    print("emulator stopped" + (" (Ctrl-C)" if rc else ""), flush=True)
    return rc

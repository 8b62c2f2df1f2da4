"""The `febed` command line.

    febed run CASE.toml [--set section.key=value ...] [--overwrite]   run a case (also under mpirun -n N)
    febed run CASE.toml --restart [CHECKPOINT]                        continue a run from its newest checkpoint
    febed check CASE.toml [--set ...]                                 validate a case, its mesh and bed, run nothing
    febed params [SECTION]                                            every parameter: default, unit, help
    febed status RUN_DIR [...]                                        state, progress, newest checkpoint of runs
    febed mesh NAME [--level L] [--cell C] [--size H] [--extent ...] -o FILE.msh   build a built-in mesh
    febed post RUN_DIR [--window T0 T1] ...                            time-averaged fields, profiles, series
    febed study STUDY.toml [--list | --jobs FILE]                      run / resume / compare a case family
    febed compare RUN_DIR RUN_DIR ... [--labels ...] [--window T0 T1]  one table + figures of separate runs

Errors in the user's input (case, mesh, bed file, checkpoint, output folder, values a solver refuses) are
printed as one clear message and exit with status 2, before anything runs: `febed run` and `febed check` run
the pre-flight checks of `febed.preflight` (mesh tags, bed file against the case, the run's cost; `--force`
runs a case whose estimate is refused as absurd); a run that fails (a particle escaping, ...) exits with status 3
after writing its last good state as a checkpoint, and so does a run stopped by an output error (a full disk:
`febed.runs.lifecycle.OutputFailure`); a run stopped by SIGINT/SIGTERM/SIGUSR1 writes a checkpoint and exits with 128 +
the signal number (130, 143, 138), also when stopped during start-up (status.json then says so); a traceback
means a bug in febed (`febed run -v` shows the traceback of a refused value too). A bug met while a run steps
(`febed.runs.lifecycle.InternalError`) is logged with its traceback, recorded as an internal error in
status.json, and exits with status 3 after writing the last good state (on one process). A failure or a bug
met by one rank of several ends every rank's process (`_end_alone`: MPI_Abort with the same status).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from mpi4py import MPI

from febed.case import CaseError, load_case
from febed.io.checkpoint import FOLDER, CheckpointError, checkpoint_identity, remove_temporaries
from febed.io.rundir import (
    RESOLVED_CASE,
    OutputError,
    _header,
    atomic_write_text,
    describe_run,
    get_logger,
    held_lock,
    lock_output,
    prepare_output,
    release_output,
    running_process,
)
from febed.meshing import GEOMETRIES, PSEUDO2D_LEVELS, MeshError, build_msh
from febed.post import cli as post_cli
from febed.preflight import mesh_name, preflight
from febed.restart import RESTARTABLE, case_changes, check_restartable, checkpoint_differences, read_resolved
from febed.schema import BOUNDARY, SCHEMA, describe

# run.mode -> "module:function" running a case of that mode as `function(case, outdir, log, restart=None)`,
# imported when a run starts (the modules load DOLFINx and Numba); a mode whose module is absent is reported.
RUNNERS = {
    "dem": "febed.runs.dem:run",
    "gas": "febed.runs.gas:run",
    "cfd-dem": "febed.runs.coupled:run_coupled",
    "one-way": "febed.runs.oneway:run",
}


class UserError(Exception):
    """An input problem reported as a message, not a traceback."""


def _say(msg: str, err: bool = False) -> None:
    if MPI.COMM_WORLD.rank == 0:
        print(msg, file=sys.stderr if err else sys.stdout, flush=True)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="febed", description="CFD-DEM for gas-solid fluidized beds.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def with_case(sp):
        sp.add_argument("case", help="TOML case file")
        sp.add_argument(
            "--set",
            dest="overrides",
            action="append",
            default=[],
            metavar="SECTION.KEY=VALUE",
            help="override a case parameter (repeatable), e.g. --set gas.density=1.165",
        )

    r = sub.add_parser("run", help="run a case")
    with_case(r)
    r.add_argument("--overwrite", action="store_true", help="replace an existing output folder written by febed")
    r.add_argument(
        "--restart",
        nargs="?",
        const="latest",
        metavar="CHECKPOINT",
        help="continue the run in the case's output folder from its newest valid checkpoint (or from this "
        "checkpoint file, or the newest one in this folder)",
    )
    r.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    force_help = (
        "run even if the pre-flight estimate refuses the run as absurd (DEM sub-steps per gas step, wall time, memory)"
    )
    r.add_argument("--force", action="store_true", help=force_help)
    c = sub.add_parser("check", help="validate a case, its mesh tags and bed file, and estimate the run")
    with_case(c)
    c.add_argument("--force", action="store_true", help=force_help)
    pa = sub.add_parser("params", help="list every case parameter with default, unit and help")
    pa.add_argument("section", nargs="?", help="only this section (e.g. gas, contact, gas.boundary)")
    m = sub.add_parser("mesh", help="build a built-in mesh as a gmsh .msh file")
    m.add_argument("name", choices=GEOMETRIES)
    m.add_argument("--level", default="coarse", choices=list(PSEUDO2D_LEVELS), help="pseudo2d: seed 001 Table 2")
    m.add_argument("--cell", default=None, help="hexahedron|tetrahedron (pseudo2d), quadrilateral|triangle (wang2d)")
    m.add_argument("--size", type=float, default=0.005, help="cell size of unstructured meshes [m]")
    m.add_argument("--extent", type=float, nargs="+", help="box: its lengths lx ly [lz] [m]")
    m.add_argument("-o", "--output", required=True, help="output file (.msh)")
    st = sub.add_parser("status", help="state, progress and newest checkpoint of run folders")
    st.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="output folder(s) of febed runs")
    post_cli.add_post_parser(sub)
    post_cli.add_study_parser(sub)
    post_cli.add_compare_parser(sub)
    return p


def cmd_params(args) -> int:
    """Print every declared parameter (generated from febed/schema.py)."""
    sections = dict(SCHEMA)
    sections["gas.boundary.<tag>"] = BOUNDARY
    if args.section:
        want = "gas.boundary.<tag>" if args.section.startswith("gas.boundary") else args.section
        if want not in sections:
            raise UserError(f"no section {args.section!r}; sections: {', '.join(sections)}")
        sections = {want: sections[want]}
    for sec, params in sections.items():
        print(f"[{sec}]")
        for key, par in params.items():
            print("  " + describe(sec, key, par))
        print()
    return 0


def cmd_status(args) -> int:
    """Describe run folders (`febed.io.rundir.describe_run`); status 2 if one is not a febed run folder."""
    for d in args.run_dirs:
        _say(describe_run(Path(d)))
    missing = [d for d in args.run_dirs if not (Path(d) / RESOLVED_CASE).is_file()]
    return 2 if missing else 0


def cmd_check(args) -> int:
    """Validate the case, its mesh and bed and estimate the run (`febed.preflight`) without writing anything."""
    case = load_case(args.case, args.overrides)
    pf = preflight(case, force=args.force)
    for note in pf.notes:
        _say(f"note: {note}")
    _say(
        f"{args.case}: OK — mode {case.run.mode}, {mesh_name(case)} ({pf.mesh['cells']} cells, tags "
        f"{', '.join(pf.tags)}), output to {case.output_dir()}\n{pf.estimate.text()}"
    )
    return 0


def cmd_mesh(args) -> int:
    """Build a built-in mesh (rank 0 only)."""
    if MPI.COMM_WORLD.rank == 0:
        kw = {"extent": args.extent} if args.name == "box" else {}
        out = build_msh(args.name, args.output, level=args.level, cell=args.cell, size=args.size, **kw)
        print(f"wrote {out}")
    return 0


def cmd_run(args) -> int:
    """Validate, lock and prepare the output folder, and hand the case to the runner of its mode.

    The folder's lock (`febed.io.rundir.lock_output`) is taken before anything is written to the folder and
    released when the run ends, however it ends. Until the run's own signal handlers take over, a stop signal
    stops at once (a KeyboardInterrupt carrying the signal as `signum`). Once the folder is the run's, an error
    or signal the run itself did not record (start-up: mesh, bed, solver, output files) is written to
    febed.log and status.json.
    """
    restore_signals = _catch_startup_signals()
    try:
        return _run(args)
    except BaseException as e:
        stop = _startup_stop(e)
        if stop is e:
            raise
        raise stop from None
    finally:
        restore_signals()


_STARTUP_SIGNAL = [0]  # the stop signal received during start-up, if any


def _stop_exception(signum: int) -> KeyboardInterrupt:
    import signal

    stop = KeyboardInterrupt(signal.Signals(signum).name)
    stop.signum = signum
    return stop


def _startup_stop(error: BaseException) -> BaseException:
    """The stop signal's KeyboardInterrupt if one came during start-up, whatever `error` it surfaced as, else `error`.

    An exception raised by a signal handler inside a library call can come out as another one (ctypes reports
    it as the ArgumentError of the call it interrupted).
    """
    if not _STARTUP_SIGNAL[0] or isinstance(error, KeyboardInterrupt) or hasattr(error, "signum"):
        return error
    return _stop_exception(_STARTUP_SIGNAL[0])


def _catch_startup_signals():
    """Make SIGINT/SIGTERM/SIGUSR1 raise KeyboardInterrupt (with `signum`); returns the restorer (main thread only)."""
    import signal
    import threading

    _STARTUP_SIGNAL[0] = 0
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(signum, frame):
        _STARTUP_SIGNAL[0] = signum
        raise _stop_exception(signum)

    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)}
    return lambda: [signal.signal(k, v) for k, v in old.items()]


def _run(args) -> int:
    from febed.runs.lifecycle import forget_state, record_exit

    case = load_case(args.case, args.overrides)
    module, function = RUNNERS[case.run.mode].split(":")
    try:
        runner = importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name and module.startswith(e.name):
            raise UserError(
                f"[run] mode = {case.run.mode!r} is not available in this version of febed "
                f"({module} is missing); see the features table in README.md"
            ) from None
        raise
    if args.restart is not None:
        if args.overwrite:
            raise UserError("--restart continues the run in the output folder: it cannot be combined with --overwrite")
        if case.run.mode not in RESTARTABLE:
            raise UserError(
                f"--restart is available for [run] mode = {' or '.join(map(repr, RESTARTABLE))}, not {case.run.mode!r}"
            )
    pf = preflight(case, force=args.force)  # mesh, bed and estimate: refused before the folder is touched
    case = pf.case  # with the bed's particles if it is authoritative
    held = held_lock(case.output_dir()) is not None  # by this process already (the Python API): kept
    try:
        if args.restart is None:
            outdir, checkpoint, meta = prepare_output(case, overwrite=args.overwrite), None, {}
        else:
            outdir, checkpoint, meta = _restart_target(case, args.restart, pf)
        forget_state(outdir)
        log = get_logger(outdir, verbose=args.verbose)
        try:
            from febed.io.fields import remove_temporaries as remove_field_temporaries

            lock = held_lock(outdir)
            if lock is not None and lock.note:
                log.warning(f"note: {lock.note}")
            for gone in remove_temporaries(outdir / FOLDER) if MPI.COMM_WORLD.rank == 0 else []:
                log.info(f"removed {gone.name}: the unfinished checkpoint of a run killed while writing it")
            for gone in remove_field_temporaries(outdir) if MPI.COMM_WORLD.rank == 0 else []:
                log.info(f"removed {gone.parent.name}/{gone.name}: an unfinished field file of a run killed writing it")
            for note in pf.notes:
                log.warning(f"note: {note}")
            log.info(pf.estimate.text())
            if checkpoint is None:
                log.info(f"febed: case {case.name} ({case.path}), mode {case.run.mode}, {MPI.COMM_WORLD.size} rank(s)")
                log.info(f"output folder: {outdir}")
                getattr(runner, function)(case, outdir, log)
            else:
                log.info(f"febed: case {case.name} ({case.path}), restart, {MPI.COMM_WORLD.size} rank(s)")
                getattr(runner, function)(case, outdir, log, restart=checkpoint)
        except BaseException as e:
            t, step = float(meta.get("time", 0.0)), int(meta.get("step", 0))
            stop = _startup_stop(e)
            alone = _maybe_alone(stop)
            if alone:
                e.alone = True
            record_exit(outdir, log, stop, case.run.end_time, t, step, restart=checkpoint is not None, alone=alone)
            raise
        MPI.COMM_WORLD.barrier()  # every rank is done with the folder
    finally:
        if not held:
            release_output(case.output_dir())
    return 0


def _maybe_alone(error: BaseException) -> bool:
    """Whether `error`, met on one of several ranks, may have been met by this rank alone (`_end_alone`).

    Stop signals reach every rank, input errors are checked on every rank alike, and failures of the simulation
    are agreed over the ranks; any other error (a bug, memory) may be this rank's only.
    """
    from febed.dem.solver import DEMFailure
    from febed.runs.lifecycle import InternalError, Interrupted
    from febed.solver import RunFailure

    if MPI.COMM_WORLD.size == 1 or not isinstance(error, Exception) or hasattr(error, "alone"):
        return bool(getattr(error, "alone", False))
    agreed = (CaseError, MeshError, OutputError, UserError, CheckpointError, RunFailure, DEMFailure, Interrupted)
    return not isinstance(error, (*agreed, InternalError))


def _restart_target(case, restart: str, pf=None) -> tuple[Path, Path, dict]:
    """The run folder, the checkpoint file to continue and its meta record (collective).

    Refuses, before anything is written, a checkpoint that does not read, is of another mode, is past the
    end time or belongs to another run (`febed.restart.checkpoint_differences` against the case, its mesh and
    particles from the pre-flight `pf`), and case changes a restart cannot take. Only then is an accepted
    change written to the resolved case.
    """
    outdir = case.output_dir()
    if not (outdir / RESOLVED_CASE).is_file():
        raise UserError(f"--restart: {outdir} holds no febed run ({RESOLVED_CASE} missing); run without --restart")
    lock_output(outdir)  # before anything is written; released by `cmd_run`
    pid = MPI.COMM_WORLD.bcast(running_process(outdir) if MPI.COMM_WORLD.rank == 0 else None, root=0)
    if pid is not None:
        raise UserError(
            f"--restart: the run in {outdir} is still going (process {pid} on this machine): two runs would write "
            f"the same files. Stop it first (kill -USR1 {pid} writes a checkpoint), then restart"
        )
    checkpoint = outdir / FOLDER if restart == "latest" else Path(restart)
    if not checkpoint.exists():
        raise UserError(f"--restart: checkpoint {checkpoint} does not exist")
    accepted, refused = case_changes(read_resolved(outdir), case.to_toml())
    if refused:
        raise UserError(
            "--restart: the case changed in parameters a run cannot change midway:\n  "
            + "\n  ".join(refused)
            + "\nstart a new run (another output directory) to change them"
        )
    checkpoint, meta, ident, skipped = checkpoint_identity(checkpoint)
    for why in skipped:
        _say(f"febed: note: skipped a newer checkpoint that does not read: {why}", err=True)
    check_restartable(meta, case)
    mesh, particles = (pf.mesh, pf.estimate.particles) if pf is not None else (None, None)
    if case.run.mode == "gas":
        particles = None
    differences = checkpoint_differences(ident, meta, case, mesh, particles)
    if differences:
        raise UserError(
            f"--restart: the checkpoint {checkpoint} belongs to another run than this case's:\n  "
            + "\n  ".join(differences)
            + "\n(checkpoint -> case); continue a checkpoint with the case it was written by"
        )
    if accepted and MPI.COMM_WORLD.rank == 0:
        _say("febed: restart with changed parameters:\n  " + "\n  ".join(accepted))
        text = read_resolved(outdir)
        atomic_write_text(outdir / f"case.before-restart-{len(list(outdir.glob('case.before-restart-*')))}.toml", text)
        atomic_write_text(outdir / RESOLVED_CASE, _header(case) + case.to_toml())
    MPI.COMM_WORLD.barrier()
    return outdir, checkpoint, meta


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `febed` console script; returns the exit status."""
    args = _parser().parse_args(argv)
    restore_signals = _catch_startup_signals() if args.command == "run" else (lambda: None)
    try:
        return _main(args)
    except KeyboardInterrupt as e:  # a stop signal while febed's modules were being imported
        signum = getattr(e, "signum", 2)
        _say(f"febed: stopped by {'Ctrl-C' if signum == 2 else e.args[0]} during start-up", err=True)
        return 128 + signum
    except Exception as e:  # a bug: its traceback, then on several ranks the whole job ends if it was this rank's
        if getattr(e, "alone", False) and MPI.COMM_WORLD.size > 1:
            import traceback

            traceback.print_exc()
            _end_alone(e, 1)
        raise
    finally:
        restore_signals()


def _main(args) -> int:
    from febed.dem.solver import DEMFailure
    from febed.runs.lifecycle import InternalError, Interrupted, StopNow
    from febed.solver import RunFailure

    commands = {
        "run": cmd_run,
        "check": cmd_check,
        "params": cmd_params,
        "mesh": cmd_mesh,
        "status": cmd_status,
        "post": post_cli.cmd_post,
        "study": post_cli.cmd_study,
        "compare": post_cli.cmd_compare,
    }
    try:
        return commands[args.command](args)
    except CaseError as e:
        _say(f"febed: error in {e}", err=True)
    except (MeshError, OutputError, UserError) as e:
        _say(f"febed: error: {e}", err=True)
    except RunFailure as e:
        _say(f"febed: the run failed: {e}", err=True)
        return _end_alone(e, 3)
    except DEMFailure as e:  # a pure-DEM run (a coupled run turns it into a RunFailure)
        _say(f"febed: the run failed: the particles blew up: {e}", err=True)
        return 3
    except InternalError as e:  # a bug met while the run stepped: its traceback is in the log already
        _say(f"febed: the run stopped on an {e}", err=True)
        return _end_alone(e, 3)
    except Interrupted as e:
        _say(f"febed: {e}", err=True)
        return _end_alone(e, 128 + e.signum)
    except KeyboardInterrupt as e:  # a stop signal during start-up (building a mesh, packing a bed), or Ctrl-C
        signum = getattr(e, "signum", 2)
        name = "Ctrl-C" if signum == 2 else e.args[0]
        if isinstance(e, StopNow):  # a second signal while the run was closing its files
            _say(f"febed: stopped at once by a second {e.args[0]}", err=True)
        else:
            during = " during start-up, before the run's first step" if args.command == "run" else ""
            _say(f"febed: stopped by {name}{during}", err=True)
        return 128 + signum
    except CheckpointError as e:
        _say(f"febed: error: {e}", err=True)
    except MemoryError as e:
        _say("febed: the run failed: out of memory (`febed check` estimates what a case needs)", err=True)
        return _end_alone(e, 3)
    except ValueError as e:  # a value the solvers refuse, with their message (-v shows the traceback)
        if getattr(args, "verbose", False):
            raise
        _say(f"febed: error: {e}", err=True)
        return _end_alone(e, 2)
    return 2


def _end_alone(error: BaseException, code: int) -> int:
    """`code`; but when `error` stopped this rank alone (its `alone`), end every rank's process with `code`.

    The other ranks may be waiting in a collective call, and this process cannot exit normally either: PETSc
    frees its objects at exit collectively (petsc4py's finalization), which would wait for them forever.
    MPI_Abort ends the whole job, and mpirun exits with `code`; the status, log and message are written.
    """
    if getattr(error, "alone", False) and MPI.COMM_WORLD.size > 1:
        import logging

        sys.stdout.flush()
        sys.stderr.flush()
        logging.shutdown()
        MPI.COMM_WORLD.Abort(code)
    return code


if __name__ == "__main__":
    sys.exit(main())

"""`photopft batch`: every session of a folder processed on a Dask distributed cluster.

One task per session, each the same `process_session` that `photopft process` runs (one worker
process per task, its heads one after the other), so a results file from `batch` equals one from
`process`. A LocalCluster on this machine by default; `--scheduler tcp://HOST:8786` sends the
tasks to a running cluster whose workers see the same paths (a shared file system). Resumable: a
session whose results file is already there and complete is skipped. A session that fails is
reported in one line and the others go on.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass
from pathlib import Path

import h5py

from app.errors import UserError

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)

RESULTS_SUFFIX = "-results.h5"


@dataclass(frozen=True)
class BatchOptions:
    """The `process` options a batch applies to every session."""
    every: int | None = None
    full_resolution: bool = False
    calibration: Path | None = None
    threads: int | None = None  # numba threads per task (a LocalCluster shares the cores out); None: numba's own


def session_files(folder: Path) -> tuple[list[Path], list[str]]:
    """(session files, one line per file skipped and why) of a folder, in name order: results files
    and files that are not HDF5 sessions are left out."""
    from core.io.results import RESULTS_FORMAT

    sessions, skipped = [], []
    for path in sorted(folder.glob("*.h5")):
        try:
            with h5py.File(path, "r") as f:
                kind = str(f.attrs.get("format", ""))
                has_heads = "heads" in f and "rig" in f
        except (OSError, ValueError):
            skipped.append(f"{path.name}: cannot be opened (truncated, damaged or not HDF5; `photopft validate` "
                           f"and `photopft recover` say more)")
            continue
        if kind == RESULTS_FORMAT:
            continue
        if not has_heads:
            skipped.append(f"{path.name}: not a photopft session (no /rig and /heads)")
            continue
        sessions.append(path)
    return sessions, skipped


def results_path(session: Path, out_dir: Path) -> Path:
    return out_dir / f"{session.stem}{RESULTS_SUFFIX}"


def already_done(session: Path, results: Path) -> bool:
    """A complete results file of this session is there (outputs appear only when complete)."""
    from core.io.results import ResultsFile, check_results

    if not results.is_file():
        return False
    try:
        check_results(results)
        with ResultsFile(results) as r:
            return Path(r.session_name).resolve() == session.resolve()
    except Exception:  # a damaged or foreign file is processed again (written beside, then renamed)
        return False


def foreign_at_results_name(results: Path) -> str | None:
    """None when batch may write `results` (nothing there, or a results file of its own, whole or
    not); otherwise the one line why it must not (a recorded session, another file)."""
    from core.io.outputs import is_session_file
    from core.io.results import is_results_file

    if not (results.exists() or results.is_symlink()):
        return None
    if results.is_dir() or results.is_symlink():
        return f"{results} is a {'folder' if results.is_dir() else 'link'}, not a results file: left alone"
    if is_session_file(results):
        return f"{results} is a recorded session, never replaced: move it out of the results folder"
    if not is_results_file(results):
        return f"{results} is not a photopft results file: left alone (move or rename it)"
    return None


def process_one(session: str, results: str, options: BatchOptions) -> tuple[str, str | None, float]:
    """The task a Dask worker runs: (session, None or the one-line reason it failed, seconds)."""
    from core.pipeline.head_maps import use_threads
    from core.pipeline.process import process_session
    from core.calibration.rig_profile import load_profile

    started = time.perf_counter()
    if options.threads is not None:
        use_threads(options.threads)
    try:
        calibration = load_profile(options.calibration) if options.calibration is not None else None
        problem = foreign_at_results_name(Path(results))  # again at the task: the folder may have changed
        if problem is not None:
            return session, problem, time.perf_counter() - started
        process_session(session, results, calibration=calibration, every=options.every, workers=1,
                        binning=1 if options.full_resolution else None)
    except Exception as exc:  # a task's boundary: any failure is this session's one line, never the batch's
        lines = str(exc).splitlines()
        return session, (lines[0] if lines else type(exc).__name__), time.perf_counter() - started
    return session, None, time.perf_counter() - started


def add_batch(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("batch", help="process every session of a folder on a Dask cluster",
                       description="Each session of FOLDER processed as `photopft process` does, one task per "
                                   "session, on a Dask LocalCluster of this machine (or --scheduler ADDRESS). "
                                   "Results go to OUTDIR/<session>-results.h5; sessions already processed there "
                                   "are skipped, so an interrupted batch goes on where it stopped.")
    p.add_argument("folder", type=Path, help="folder of session files (.h5)")
    p.add_argument("-o", "--output-dir", type=Path, required=True, help="folder for the results files")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (default: a LocalCluster here)")
    p.add_argument("--workers", type=int, default=None,
                   help="LocalCluster worker processes (default: one per core)")
    p.add_argument("--every", type=int, default=None, help="as for `photopft process`")
    p.add_argument("--full-resolution", action="store_true", help="as for `photopft process`")
    p.add_argument("--rig", type=Path, help="a lights calibration profile for every session, as for `process`")
    p.set_defaults(run=run_batch)


def run_batch(args: argparse.Namespace) -> int:
    from app.progress import Progress

    if not args.folder.is_dir():
        raise UserError(f"{args.folder} is not a folder")
    if args.workers is not None and args.workers < 1:
        raise UserError("--workers must be 1 or more")
    if args.output_dir.exists() and not args.output_dir.is_dir():
        raise UserError(f"-o {args.output_dir} is a file, not a folder")
    sessions, skipped = session_files(args.folder)
    for line in skipped:
        print(f"  skipped {line}")
    args.output_dir.mkdir(parents=True, exist_ok=True)
    todo = [s for s in sessions if not already_done(s, results_path(s, args.output_dir))]
    print(f"{len(sessions)} session(s) in {args.folder}: {len(sessions) - len(todo)} already processed, "
          f"{len(todo)} to do")
    refused = []
    for s in todo:
        problem = foreign_at_results_name(results_path(s, args.output_dir))
        if problem is not None:
            refused.append(s)
            print(f"  {s.name}: refused: {problem}")
    todo = [s for s in todo if s not in refused]
    if not todo:
        return 1 if refused else 0
    local_workers = None if args.scheduler else (args.workers or os.cpu_count() or 1)
    threads = max(1, (os.cpu_count() or 1) // local_workers) if local_workers else None
    options = BatchOptions(args.every, args.full_resolution, args.rig, threads)
    failures = _run_on_cluster(todo, args, options, Progress(f"batch of {len(todo)}"))
    done = len(todo) - len(failures)
    print(f"processed {done} of {len(todo)} session(s) into {args.output_dir}"
          + (f"; {len(failures)} failed" if failures else "") + (f"; {len(refused)} refused" if refused else ""))
    return 1 if failures or refused else 0


def _run_on_cluster(todo: list[Path], args: argparse.Namespace, options: BatchOptions, progress) -> list[str]:
    import logging

    import dask
    from distributed import Client, LocalCluster, as_completed

    # Dask starts its workers with MALLOC_TRIM_THRESHOLD_=65536 (memory handed back to the system at
    # once) and one OpenMP thread: each map's large arrays then went back and forth to the kernel,
    # a session took 3 times as long as under `process` (sys time as high as user). The workers
    # keep glibc's own threshold; numba's threads are set per task (BatchOptions.threads).
    dask.config.set({"distributed.nanny.pre-spawn-environ": {}})

    logging.getLogger("distributed").setLevel(logging.WARNING)  # the cluster's chatter stays out of the batch's report
    cluster = None
    try:
        if args.scheduler:
            client = Client(args.scheduler, timeout="10s")
        else:
            cluster = LocalCluster(n_workers=args.workers or os.cpu_count() or 1, threads_per_worker=1,
                                   processes=True, dashboard_address=":0", silence_logs=40)
            client = Client(cluster)
    except (OSError, TimeoutError) as exc:
        raise UserError(f"--scheduler {args.scheduler}: cannot reach it ({str(exc).splitlines()[0]})") from exc
    failures: list[str] = []
    try:
        print(f"Dask dashboard: {client.dashboard_link}")
        futures = {client.submit(process_one, str(s), str(results_path(s, args.output_dir)), options, pure=False): s
                   for s in todo}
        finished = 0
        with progress:
            for future in as_completed(futures):
                session = futures[future]
                try:
                    _, problem, seconds = future.result()
                except Exception as exc:  # the worker itself died (memory, a signal): said, not raised
                    problem, seconds = f"the worker stopped ({type(exc).__name__}: {exc})", float("nan")
                finished += 1
                progress(finished / len(todo), session.name)
                if problem is None:
                    print(f"  {session.name}: done in {seconds:.1f} s")
                else:
                    failures.append(session.name)
                    print(f"  {session.name}: failed: {problem}")
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return failures

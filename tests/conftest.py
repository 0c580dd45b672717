import contextlib
import fcntl
import importlib
import importlib.util
import io
import json
import mmap
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

REPO = Path(__file__).resolve().parent.parent

# The small runs of the end-to-end tests, in one place (a later key=value overrides an
# earlier one): routes, and auto-encoders small enough to train in a second.
TINY_ROUTE = ["data.n_frames=400", "split.n_train=150", "split.n_test=60", "split.gap=10"]
# The small sweep's route is the tiny one: the same shapes, so every program one compiles
# the other reads back (the session's XLA cache) or finds traced (the same test process).
SMALL_ROUTE = TINY_ROUTE
TINY_MODELS = ["fae.hidden=32", "cae.channels=[4,8]", "cae.code_channels=2"]
# A small but complete sweep: the three default pairs, every method, three removed-PC counts
# and tiny auto-encoders trained for two epochs.
SMALL = [*SMALL_ROUTE, "removed_pcs=[0,5,20]", *TINY_MODELS, "train.epochs=2", "fae.epochs=2"]


# Every subprocess a test starts ends within this (the per-test limit in pyproject.toml is
# longer, so a hung subprocess fails its test with its own message and output, not the
# runner's stack dump).
PROCESS_TIMEOUT_S = 240


def env_with_repo(**extra: str) -> dict:
    """The environment a child process of a test runs in: this one, the repository on
    PYTHONPATH, and ``extra``."""
    return {**os.environ, "PYTHONPATH": str(REPO), **extra}


def _kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL the child's whole process group (it leads one: ``start_new_session``)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)


def _tail(text: str | None, n: int = 3000) -> str:
    return (text or "")[-n:]


def run_process(
    cmd: list[str], *, timeout: float = PROCESS_TIMEOUT_S, env: dict | None = None, **kwargs
) -> subprocess.CompletedProcess:
    """``subprocess.run(cmd, capture_output=True, text=True)`` in the repository, in a new
    process group that is killed whole when ``timeout`` seconds pass; the test then fails
    with one message naming the command and the end of its output."""
    with subprocess.Popen(
        cmd,
        cwd=kwargs.pop("cwd", REPO),
        env=env_with_repo() if env is None else env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        **kwargs,
    ) as proc:
        expired = False
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            expired = True
            _kill_group(proc)
            out, err = proc.communicate()
        except BaseException:  # the test's own limit, Ctrl-C: leave nothing running
            _kill_group(proc)
            raise
    if expired:
        pytest.fail(
            f"{shlex.join(map(str, cmd))[:300]} did not finish within {timeout:g} s; its "
            f"process group was killed.\nstdout: ...{_tail(out)}\nstderr: ...{_tail(err)}",
            pytrace=False,
        )
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


@contextlib.contextmanager
def started(
    cmd: list[str], *, timeout: float = PROCESS_TIMEOUT_S, **kwargs
) -> Iterator[subprocess.Popen]:
    """A child process the test talks to while it runs (``Popen`` arguments; text mode,
    the repository's environment, its own process group). Whatever happens in the block,
    the group is killed at its end and the child reaped; a watchdog kills it after
    ``timeout`` s (its pipes then reach their end, so no read blocks for ever) and the test
    fails with a message saying so."""
    kwargs.setdefault("env", env_with_repo())
    proc = subprocess.Popen(cmd, cwd=REPO, text=True, start_new_session=True, **kwargs)
    expired = threading.Event()
    watchdog = threading.Timer(timeout, lambda: (expired.set(), _kill_group(proc)))
    watchdog.daemon = True
    watchdog.start()
    try:
        yield proc
    finally:
        watchdog.cancel()
        _kill_group(proc)
        proc.wait()
        for stream in (proc.stdin, proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
        if expired.is_set():
            pytest.fail(
                f"{shlex.join(map(str, cmd))[:300]} was still running after {timeout:g} s; "
                "its process group was killed",
                pytrace=False,
            )


def run_cli(*args: str, env: dict | None = None, timeout: float = PROCESS_TIMEOUT_S):
    """``python -m experiments.sweep ARGS`` in a fresh interpreter, as a user runs it, with
    ``env`` added to the environment (``run_process``: killed after ``timeout`` s).

    Unless the test names one, models are checkpointed next to the logdir (in the test's
    own tmp folder), not in the repository's checkpoints/.
    """
    logdirs = [a.split("=", 1)[1] for a in args if a.startswith("logdir=")]
    if logdirs and not any(a.startswith("train.checkpoint_dir=") for a in args):
        args = (*args, f"train.checkpoint_dir={Path(logdirs[-1]).parent / 'checkpoints'}")
    return run_process(
        [sys.executable, "-m", "experiments.sweep", *args],
        env=env_with_repo(**(env or {})),
        timeout=timeout,
    )


def run_here(*args: str, path: Iterable[str | Path] = ()) -> subprocess.CompletedProcess:
    """``python -m experiments.sweep ARGS`` run by its ``main`` in this process, its output
    captured: wherever what is tested is what the sweep prints, writes or refuses, not the
    command line's start, a process's signals or its exit (a fresh interpreter costs each
    run JAX's import, and every program it runs is compiled or read from the cache again).
    Models are checkpointed next to the logdir, as ``run_cli`` does.

    ``path``: folders put in front of ``sys.path`` for the run, as ``PYTHONPATH`` would be
    for a fresh interpreter (a user's method modules); the modules imported from them are
    forgotten afterwards, so the next run imports them afresh, as a new process would.

    A sweep here holds its logdir's lock, and the checkpoint folder of every model it
    trained or restored, until the test runner exits (``lock_folder``: the kernel drops a
    lock when its process ends): a later sweep in another process (a test's subprocess,
    another pytest-xdist worker) that needs one of them must use a copy."""
    from experiments import sweep

    logdirs = [a.split("=", 1)[1] for a in args if a.startswith("logdir=")]
    if logdirs and not any(a.startswith("train.checkpoint_dir=") for a in args):
        args = (*args, f"train.checkpoint_dir={Path(logdirs[-1]).parent / 'checkpoints'}")
    folders = [str(Path(p).resolve()) for p in path]
    saved_path, dont_write_bytecode = list(sys.path), sys.dont_write_bytecode
    _forget_modules(folders)  # also another folder's module of the same name
    sys.path[:0] = folders
    sys.dont_write_bytecode = True  # a module rewritten under the same name is read again
    importlib.invalidate_caches()
    out, err = io.StringIO(), io.StringIO()
    handler = signal.getsignal(signal.SIGTERM)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = sweep.main(list(args))
    finally:
        signal.signal(signal.SIGTERM, handler)
        sys.path[:], sys.dont_write_bytecode = saved_path, dont_write_bytecode
        _forget_modules(folders)
    return subprocess.CompletedProcess(
        ["experiments.sweep", *args], code, out.getvalue(), err.getvalue()
    )


def sweep_rows(
    *args: str, run: Callable = run_here, **kwargs
) -> tuple[list, subprocess.CompletedProcess]:
    """A sweep that must succeed: ``run(*args, **kwargs)`` (``run_here``, or ``run_cli`` for
    a fresh interpreter), asserted to exit 0 (the end of its stderr in the message).
    Returns ``(rows, proc)``: the rows of ``results.csv`` in the logdir ``args`` name
    (``read_results``) and the finished process, for what the test reads of its output."""
    from vpr_jax.outputs.results import read_results

    logdirs = [a.split("=", 1)[1] for a in args if a.startswith("logdir=")]
    assert logdirs, f"sweep_rows: no logdir= among {args}"
    proc = run(*args, **kwargs)
    assert proc.returncode == 0, f"exit {proc.returncode}, stderr: ...{_tail(proc.stderr)}"
    return read_results(Path(logdirs[-1]) / "results.csv"), proc


def _forget_modules(folders: list[str]) -> None:
    """Drop from ``sys.modules`` every module imported from ``folders`` and every module
    named like one of theirs (``name.py`` or a package ``name/``)."""
    if not folders:
        return
    names = {p.stem for f in folders for p in Path(f).iterdir() if p.suffix == ".py" or p.is_dir()}
    for name, module in list(sys.modules.items()):
        file = getattr(module, "__file__", None) or ""
        if name.split(".")[0] in names or any(file.startswith(f + os.sep) for f in folders):
            del sys.modules[name]


def assert_one_line_error(
    proc: subprocess.CompletedProcess, *words: str, returncode: int = 2
) -> str:
    """What the suite answers bad input (exit code 2) or a fault it cannot work around (1)
    with: that exit code, one line on stderr that starts with ``error: `` and holds every
    one of ``words``, no traceback anywhere. Returns the line."""
    assert proc.returncode == returncode, (proc.returncode, _tail(proc.stdout), _tail(proc.stderr))
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's: without it (-p no:xdist), unused
def pytest_xdist_auto_num_workers(config):
    """``-n auto`` (pyproject.toml): one test process more than the cores this one may use.
    Tests wait on their subprocesses, on Ray's start and on signals, and a spare process
    keeps the cores busy meanwhile: 6:02-6:08 against 6:23-6:55 with one per core (the
    whole suite, 2-core AMD EPYC, 2026-12-07)."""
    return len(os.sched_getaffinity(0)) + 1


XLA_CACHE = pytest.StashKey[str]()


def pytest_configure(config):
    """The environment of every test process and every process it starts, set once by the
    first process (pytest-xdist's workers inherit it):

    - one thread each for XLA's and numpy's linear algebra: the suite runs a test process per
      core (and one more), each starting sweeps of its own, and thread pools
      sized for the whole machine then spin against each other (the suite took 4 min 40 s
      on 2 cores with them, 4 min 15 s without);
    - XLA's CPU code generated without LLVM's optimisation passes
      (``--xla_backend_optimization_level=0``) and by XLA's older fusion code generator,
      which compiles in half the time of the MLIR one (``--xla_cpu_use_fusion_emitters=false``
      where the installed jaxlib has the flag): the suite's programs are tiny and most of
      their time was compiling them; the same computations, rounded as that code rounds
      them (no check here depends on the last bits: oracles have tolerances, and runs
      compared with each other run under the same flags). The suite took 6 min 22 s with
      XLA's defaults, 5 min 19-22 s without LLVM's passes, 4 min 12 s with the older
      generator as well (2 cores, 2026-12-05). Each program's machine code is generated in
      one piece, not split over a pool of threads
      (``--xla_cpu_parallel_codegen_split_count=1``, where jaxlib has it): a small sweep's
      137 programs compiled in 2.9 CPU-s instead of 3.8 (2-core AMD EPYC, 2026-12-07); its
      code differs in rounding (lda's ``val_margin`` in the 6th digit), as the flags above
      already make it. JAX looks for no accelerator (``JAX_PLATFORMS=cpu`` unless set);
    - one cache of XLA's compiled programs for the session: the suite's many small sweeps
      compile the same programs, and reading them back halves each sweep's time. The
      folder is deleted when the session ends. JAX writes an entry without a lock; an entry
      read while being written fails to decompress and JAX compiles the program again (the
      warnings of that are silenced, so that they do not break a test that reads stderr).
    """
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return
    folder = tempfile.mkdtemp(prefix="vpr_jax_tests_xla_cache_")
    config.stash[XLA_CACHE] = folder

    def extended(name: str, *items: str, sep: str) -> str:
        return sep.join(filter(None, [os.environ.get(name), *items]))

    cache_warnings = [
        f"ignore:Error {verb} persistent compilation cache entry" for verb in ("reading", "writing")
    ]
    os.environ.update(
        XLA_FLAGS=extended(
            "XLA_FLAGS",
            "--xla_cpu_multi_thread_eigen=false",
            "--xla_backend_optimization_level=0",
            "--xla_cpu_use_fusion_emitters=false"
            if _xla_knows("xla_cpu_use_fusion_emitters")
            else "",
            "--xla_cpu_parallel_codegen_split_count=1"
            if _xla_knows("xla_cpu_parallel_codegen_split_count")
            else "",
            sep=" ",
        ),
        JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS") or "cpu",
        OPENBLAS_NUM_THREADS="1",
        OMP_NUM_THREADS="1",
        JAX_COMPILATION_CACHE_DIR=folder,
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0",
        PYTHONWARNINGS=extended("PYTHONWARNINGS", *cache_warnings, sep=","),
    )


def _xla_knows(flag: str) -> bool:
    """Whether the installed jaxlib's XLA has ``flag``: its name in jaxlib's compiled
    libraries. XLA ends every process that is given a flag it does not know, and
    ``xla_cpu_use_fusion_emitters`` is younger than the oldest jax the project accepts
    (and may go when the older generator does)."""
    spec = importlib.util.find_spec("jaxlib")
    for lib in Path(spec.origin).parent.glob("*.so"):
        with open(lib, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
            if m.find(flag.encode()) != -1:
                return True
    return False


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    """The controller deletes the session's XLA cache. A pytest-xdist worker, which has
    told the controller its results by now, ends here without tearing down its
    interpreter: freeing a session's thousands of compiled programs took 3-4 s at the end
    of every worker (the suite waits for the last), and execnet interrupts a worker still
    busy 5 s after the controller's shutdown with SIGINT (a KeyboardInterrupt warning from
    JAX's garbage collection callback then ended the suite's output)."""
    if XLA_CACHE in config.stash:
        shutil.rmtree(config.stash[XLA_CACHE], ignore_errors=True)
    if os.environ.get("PYTEST_XDIST_WORKER"):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


def private_xla_cache(folder: Path) -> dict:
    """The environment for a sweep the test kills or limits: a copy of the session's XLA
    cache in ``folder`` (an entry it cuts short then harms only that copy)."""
    shared = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if not shared:
        return {}
    copy = shutil.copytree(shared, Path(folder) / "xla_cache", dirs_exist_ok=True)
    return {"JAX_COMPILATION_CACHE_DIR": str(copy)}


def shared_folder(tmp_path_factory, name: str, make: Callable[[Path], None]) -> Path:
    """A folder ``make(folder)`` fills once per session, whichever pytest-xdist worker asks
    first (under an exclusive file lock in the session's folder, which every worker's
    basetemp lies in); the others wait for it, then read it (read-only for every test)."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent
    folder, done = base / name, base / f"{name}.done"
    with open(base / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)  # what a failed attempt left
            folder.mkdir(parents=True)
            make(folder)
            done.touch()
    return folder


@contextlib.contextmanager
def one_ray_at_a_time(tmp_path_factory):
    """Held while a test's Ray cluster runs: tests that start one (test_cluster.py) take
    turns, whichever pytest-xdist worker runs them, so two clusters never share the cores
    at once (an exclusive lock in the session's folder)."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent
    with open(base / "ray.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        yield


def shared_sweep(tmp_path_factory, name: str, *args: str, path: Iterable[str | Path] = ()):
    """``(logdir, the finished process)`` of ``run_here(*args, path=path)`` run once per
    session into a ``shared_folder`` (read-only for every test; the worker that ran it
    holds its locks, so a test that resumes or retrains it works on a copy)."""

    def sweep(folder: Path) -> None:
        proc = run_here(*args, f"logdir={folder / 'runs'}", path=path)
        assert proc.returncode == 0, proc.stderr
        record = [proc.args, proc.returncode, proc.stdout, proc.stderr]
        (folder / "process.json").write_text(json.dumps(record))

    folder = shared_folder(tmp_path_factory, name, sweep)
    record = json.loads((folder / "process.json").read_text())
    return folder / "runs", subprocess.CompletedProcess(*record)


@pytest.fixture(scope="session")
def small_sweep(tmp_path_factory):
    """One finished small sweep shared by the end-to-end tests of every worker (read-only
    for them): ``(logdir, the finished process)``."""
    return shared_sweep(tmp_path_factory, "small_sweep", *SMALL)


@pytest.fixture(scope="session")
def cluster_benchmark(tmp_path_factory):
    """``benchmarks/cluster.py --tiny --keep``, run once per session for every test that
    reads it (its printout: test_benchmark_scripts.py; its jax.distributed run's rows:
    test_sharding.py): ``(stdout, the folder of its runs' logdirs and checkpoints)``.
    Each of its Ray runs starts and stops a Ray of its own, on ports of its own: it need
    not wait for test_cluster.py's cluster."""

    def run(folder: Path) -> None:
        script = REPO / "benchmarks" / "cluster.py"
        proc = run_process([sys.executable, str(script), "--tiny", "--keep", str(folder / "runs")])
        assert proc.returncode == 0, (proc.stdout[-3000:], proc.stderr[-3000:])
        (folder / "stdout.txt").write_text(proc.stdout)

    folder = shared_folder(tmp_path_factory, "cluster_benchmark", run)
    return (folder / "stdout.txt").read_text(), folder / "runs"


def method_settings(cfg, name: str):
    """A built-in method's settings as the plan checks them (its ``Settings``; the first
    combination of its axes), before they meet the training set."""
    from experiments.resolve import resolve
    from vpr_jax.method_table import METHODS

    return resolve(METHODS[name], cfg).combinations[0].settings


def suffix_cosine(query_desc, db_desc, starts: tuple[int, ...]):
    """Cosine similarity on descriptor suffixes ``[start:]`` for every start, (s, nq, ndb),
    from the one pass the matcher makes (``matching.suffix_dots``): what the tests compare
    with the cosine of each suffix on its own."""
    import jax.numpy as jnp

    from vpr_jax.evaluation.matching import suffix_dots, suffixes

    scores = {
        i: dot * inv_q[:, None] * inv_db[None, :]
        for i, dot, inv_q, inv_db in suffix_dots(
            suffixes(query_desc, starts), suffixes(db_desc, starts)
        )
    }
    return jnp.stack([scores[i] for i in range(len(starts))])


def numpy_cosine(q, d):
    """The oracle for cosine similarity: (n_queries, n_db), rows and columns L2-normalised."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return q @ d.T


class LogLines(list):
    """Collects what a reader or loop logs: pass it where ``log=print`` would go."""

    def __call__(self, line: str) -> None:
        self.append(line)


def read_run(path: Path) -> EventAccumulator:
    """A TensorBoard run read back by TensorBoard's own reader, keeping every event (its
    default keeps only a sample of each tag)."""
    ea = EventAccumulator(str(path), size_guidance={"scalars": 0, "tensors": 0, "images": 0})
    ea.Reload()
    return ea


def tail_validation(images, n_groups: int, fraction: float):
    """(train, val): the last ``fraction`` of each of ``n_groups`` equal consecutive groups
    held out, as the sweep's split holds out the end of each season's training stretch."""
    groups = np.split(np.asarray(images), n_groups)
    n_val = max(1, int(round(len(groups[0]) * fraction)))
    return (
        np.concatenate([g[:-n_val] for g in groups]),
        np.concatenate([g[-n_val:] for g in groups]),
    )

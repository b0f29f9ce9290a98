"""The run's plot drawn in a second process, which imports matplotlib while the run goes.

Importing matplotlib and drawing the figure is about a second of CPU, all of it after the run in
one process. ``racecar-hw sim`` starts a :class:`PlotWorker` before the run: a child Python
(``python -m racecar_hw.sim.plot_worker``) that imports :mod:`racecar_hw.sim.plot` on the
machine's other core, then waits for the one figure to draw. At the end of the run the report
hands it the same arguments :func:`racecar_hw.sim.plot.plot_run` takes (:meth:`PlotWorker.submit`)
and writes the trajectory CSV while the child draws; :meth:`PendingPlot.wait` returns when the PNG
is written. The picture is the one :func:`~racecar_hw.sim.plot.plot_run` draws in-process, byte
for byte: same function, same arguments.

Failure is never worse than no worker: a child that did not start, died, raised, or took or gave
nothing for :data:`RESULT_TIMEOUT_S` (stopped, stuck) is reported in the log (and killed) and the
figure is drawn in this process instead (where a genuine plotting error then
raises as it always did).

Interruption: the child runs in a session of its own, so a Ctrl-C at the terminal reaches only
the ``sim`` process, which handles it as before; the child ends when its standard input closes
(:meth:`PlotWorker.close`, or the parent gone for any reason). The run hands the figure over and
waits for the answer in a thread (:meth:`PendingPlot.answer`), its event loop free to act on a
Ctrl-C meanwhile: a stop request then gives the figure up (:meth:`PlotWorker.kill`) instead of
waiting up to :data:`RESULT_TIMEOUT_S` for it.

The pipe carries pickles between this process and the child it started, nothing else.
"""

from __future__ import annotations

import logging
import os
import pickle
import select
import subprocess
import sys
import time
import traceback
from pathlib import Path
from typing import IO, Any

log = logging.getLogger(__name__)

#: How long (s) :meth:`PlotWorker.close` waits for the child to end before killing it.
CLOSE_TIMEOUT_S = 5.0
#: How long (s) the run waits for the child's answer (it draws in well under a second; a child
#: stopped or stuck once held the command, Ctrl-C and all, for good): then it is killed and the
#: figure drawn in this process.
RESULT_TIMEOUT_S = 30.0


class PendingPlot:
    """A figure submitted to the worker; :meth:`wait` for it."""

    def __init__(self, worker: PlotWorker | None, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        self._worker = worker
        self._args = args
        self._kwargs = kwargs

    def answer(self) -> tuple[int, int] | None:
        """The worker's answer: the PNG's size in pixels (width, height), or None when there is no
        worker or it could not draw (or was killed, :meth:`PlotWorker.kill`). Nothing is drawn here;
        blocks, so a run's event loop asks it from a thread."""
        worker, self._worker = self._worker, None
        return worker.result() if worker is not None else None

    def wait(self) -> tuple[int, int]:
        """The PNG's size in pixels (width, height) once it is written; drawn here if the worker
        could not."""
        size = self.answer()
        if size is not None:
            return size
        from racecar_hw.sim.plot import plot_run  # noqa: PLC0415 - matplotlib, only when needed

        return plot_run(*self._args, **self._kwargs)


class PlotWorker:
    """A child process that draws one run's plot: :meth:`start`, :meth:`submit`, :meth:`close`
    (or use it as a context manager)."""

    def __init__(self, process: subprocess.Popen[bytes] | None) -> None:
        self._process = process
        self._child = process  # for kill(), from another thread than the one waiting for it

    @classmethod
    def start(cls) -> PlotWorker:
        """Start the child (it imports the plotting modules at once); a worker that could not start
        draws nothing and every figure is drawn in this process."""
        try:
            process = subprocess.Popen(
                [sys.executable, "-m", "racecar_hw.sim.plot_worker"], stdin=subprocess.PIPE,
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, start_new_session=True)
        except OSError as err:
            log.info("plot worker: not started (%s); the plot is drawn in this process", err)
            process = None
        return cls(process)

    def submit(self, path: str | Path, *args: Any, **kwargs: Any) -> PendingPlot:
        """Start drawing :func:`~racecar_hw.sim.plot.plot_run` (``path``, then its other arguments)
        in the child; at most one figure per worker."""
        call_args = (path, *args)
        process, self._process = self._process, None
        if process is None:
            return PendingPlot(None, call_args, kwargs)
        try:
            assert process.stdin is not None
            data = pickle.dumps((call_args, kwargs), protocol=pickle.HIGHEST_PROTOCOL)
            _write_all(process.stdin.fileno(), data, RESULT_TIMEOUT_S)  # more than a pipe holds
            process.stdin.close()
        except (OSError, pickle.PicklingError, TypeError, AttributeError, TimeoutError) as err:
            log.info("plot worker: the figure could not be handed over (%s); drawn here", err)
            _end(process)
            return PendingPlot(None, call_args, kwargs)
        self._process = process
        return PendingPlot(self, call_args, kwargs)

    def result(self) -> tuple[int, int] | None:
        """The child's answer to the figure submitted: its size, or None (logged) on any failure."""
        process, self._process = self._process, None
        if process is None:
            return None
        try:
            assert process.stdout is not None
            status, value = pickle.loads(_read_to_end(process.stdout.fileno(), RESULT_TIMEOUT_S))
        except (OSError, EOFError, pickle.UnpicklingError, ValueError, TimeoutError) as err:
            log.info("plot worker: no answer (%s); the plot is drawn in this process",
                     err or type(err).__name__)
            return None
        finally:
            _end(process)
        if status != "ok":
            log.info("plot worker: failed (%s); the plot is drawn in this process", value)
            return None
        return int(value[0]), int(value[1])

    def kill(self) -> None:
        """Give the figure up (a stop request while it is drawn): the child is killed, so that
        :meth:`result`, waiting for it in another thread, returns None at once."""
        child = self._child
        if child is not None and child.poll() is None:
            child.kill()

    def close(self) -> None:
        """End the child if it is still there (nothing submitted, or not waited for)."""
        process, self._process = self._process, None
        if process is not None:
            _end(process)

    def __enter__(self) -> PlotWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _write_all(fd: int, data: bytes, timeout_s: float) -> None:
    """Write ``data`` to the child's ``fd``; TimeoutError if it takes none for ``timeout_s``."""
    os.set_blocking(fd, False)
    deadline = time.monotonic() + timeout_s
    view = memoryview(data)
    while view:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError(f"the child took {len(data) - len(view)} of {len(data)} bytes in "
                               f"{timeout_s:.0f} s")
        _, writable, _ = select.select([], [fd], [], left)
        if writable:
            try:
                view = view[os.write(fd, view):]
            except BlockingIOError:
                pass


def _read_to_end(fd: int, timeout_s: float) -> bytes:
    """Everything the child writes to ``fd`` until it closes it; TimeoutError after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    chunks = []
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError(f"none in {timeout_s:.0f} s")
        readable, _, _ = select.select([fd], [], [], left)
        if readable:
            data = os.read(fd, 1 << 16)
            if not data:
                return b"".join(chunks)
            chunks.append(data)


def _end(process: subprocess.Popen[bytes]) -> None:
    """Close the pipes and reap the child, killing it if it does not end by itself."""
    for stream in (process.stdin, process.stdout):
        if stream is not None:
            try:
                stream.close()
            except OSError:
                pass
    try:
        process.wait(CLOSE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def serve(stdin: IO[bytes], stdout: IO[bytes]) -> int:
    """The child's side: import the plot, draw the one figure read from ``stdin`` (if any: EOF ends
    it quietly), answer ``("ok", (width, height))`` or ``("error", text)`` on ``stdout``."""
    from racecar_hw.sim.plot import plot_run  # noqa: PLC0415 - the point: imported while the run goes

    try:
        args, kwargs = pickle.load(stdin)
    except EOFError:
        return 0  # the run ended without a plot (interrupted, failed)
    try:
        answer: tuple[str, Any] = ("ok", plot_run(*args, **kwargs))
    except Exception:  # noqa: BLE001 - reported to the parent, which draws (and raises) itself
        answer = ("error", traceback.format_exc(limit=3))
    pickle.dump(answer, stdout, protocol=pickle.HIGHEST_PROTOCOL)
    stdout.flush()
    return 0


if __name__ == "__main__":
    # the answer is written and flushed (and the PNG closed): end without the interpreter's
    # teardown of matplotlib's modules, which the parent would otherwise wait for (about 0.1 s)
    code = serve(sys.stdin.buffer, sys.stdout.buffer)
    sys.stdout.flush()
    os._exit(code)

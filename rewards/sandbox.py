"""Sandbox for generated reward programs (LLM- or planner-written ``def reward(scene)``): the parent side.

A reward program never runs with plain ``exec`` in the training process. It goes through three layers
(docs/design.md, "The reward sandbox"):

1. the static check (:func:`rewards.program_check.check_program`), whose messages are meant for the LLM;
2. a long-lived worker process (:mod:`rewards.sandbox_worker`) with resource limits, restricted builtins,
   read-only module proxies and an audit hook, which then confines itself in the kernel (Landlock and seccomp:
   :mod:`rewards.confine`) before it reads a program;
3. this parent: a wall-clock deadline per request (kill and restart the worker, report "timed out after X s"),
   replies read as length-prefixed JSON (never pickle: a subverted worker cannot run code in the trainer) of
   bounded size, values re-checked and clamped, and a refusal to run programs where the kernel cannot confine.

:class:`RewardSandbox` owns one worker; :class:`SandboxedReward` is the callable ``batch -> tensor (B,)`` for
:class:`~rewards.composite.CompositeReward`.
"""

from __future__ import annotations

import json
import math
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rewards.confine import WEAK_SANDBOX_ENV
from rewards.program_check import ALLOWED_IMPORTS, check_program
from rewards.sandbox_worker import MAX_PRINT_CHARS, _HEADER, _clamp, _read_exact, _write_frame, describe_batch

# ------------------------------------------------------------------------------------------------------
# Limits
# ------------------------------------------------------------------------------------------------------
#: Default address-space limit of the worker (MB). Importing torch, numpy, scipy, shapely and the scene
#: code with one thread maps about 0.7 GB (VmPeak measured ~700 MB; 600 MB already fails to import
#: scipy), so 2 GB leaves ~1.3 GB for a program: orders of magnitude more than 32 bedrooms need.
DEFAULT_MEMORY_MB = 2048
#: Values are clamped to [-CLAMP, CLAMP]; NaN becomes 0 and +-inf +-CLAMP.
DEFAULT_CLAMP = 10.0
#: Largest worker reply read by the parent (bytes).
MAX_REPLY_BYTES = 4 << 20
#: The only environment variables the worker inherits (the parent's may hold API keys a program could print).
WORKER_ENV = frozenset({"PATH", "LANG", "LC_ALL", "LC_CTYPE", "TZ", "PYTHONHASHSEED"})

# ------------------------------------------------------------------------------------------------------
# Results
# ------------------------------------------------------------------------------------------------------
@dataclass
class LoadResult:
    """Outcome of :meth:`RewardSandbox.load`; ``message`` is meant for the LLM when ``ok`` is False."""

    ok: bool
    message: str


@dataclass
class ScoreResult:
    """Outcome of :meth:`RewardSandbox.score`: ``values`` (B,) float64, clamped and finite (zeros on failure);
    ``nonfinite`` NaN/inf values replaced; ``clipped`` finite values beyond the clamp bound; ``seconds``
    round-trip time; ``output`` the program's captured prints (bounded)."""

    values: np.ndarray
    ok: bool
    message: str = ""
    nonfinite: int = 0
    clipped: int = 0
    seconds: float = 0.0
    output: str = ""
    gradient: dict | None = None
    """With ``score(batch, gradient=True)``: d(sum of values) / d geometry, ``{"translations": (B, N, 3),
    "half_sizes": (B, N, 3), "yaws": (B, N)}`` float64, finite (zeros on failure)."""


class SandboxError(RuntimeError):
    """The sandbox worker cannot be started."""


# ------------------------------------------------------------------------------------------------------
# Layer 3: the parent side
# ------------------------------------------------------------------------------------------------------
class _WorkerLost(Exception):
    """The worker timed out, died or sent garbage; the message says which."""


def _death_reason(returncode: int | None, cpu_seconds: int, memory_mb: int) -> str:
    if returncode is None:
        return "stopped answering"
    if returncode < 0:
        sig = -returncode
        if sig == signal.SIGXCPU:
            return f"exceeded its CPU-time limit of {cpu_seconds} s"
        if sig == signal.SIGKILL:
            return f"was killed (SIGKILL; perhaps beyond the {memory_mb} MB memory limit)"
        if sig == signal.SIGSEGV:
            return "crashed (segmentation fault)"
        try:
            return f"died from signal {signal.Signals(sig).name}"
        except ValueError:
            return f"died from signal {sig}"
    return f"exited with status {returncode}"


_WEAK_WARNED: list = []  # the weak-sandbox warning, printed once per process


class RewardSandbox:
    """One long-lived worker process that runs one reward program at a time.

    ``timeout`` is the wall-clock deadline of each request (load or score), ``memory_mb`` the worker's
    address-space limit, ``cpu_seconds`` its CPU-time limit per request (default ``timeout + 5``),
    ``clamp`` the bound of the returned values. The worker starts at construction (its time is
    ``startup_seconds``) and restarts after a timeout or a crash, reloading the active program.
    """

    def __init__(self, room: str = "bedroom", timeout: float = 10.0, memory_mb: int = DEFAULT_MEMORY_MB,
                 cpu_seconds: int | None = None, clamp: float = DEFAULT_CLAMP, startup_timeout: float = 120.0):
        from iarcs_env.rooms import get_room

        self.room = get_room(room).name  # an unknown room fails here, not in the worker
        self.timeout = float(timeout)
        self.memory_mb = int(memory_mb)
        self.cpu_seconds = int(cpu_seconds if cpu_seconds is not None else math.ceil(self.timeout) + 5)
        self.clamp = float(clamp)
        self.startup_timeout = float(startup_timeout)
        self.code: str | None = None  # the active (last good) program
        self.startup_seconds: float | None = None
        self.confinement: dict | None = None  # the worker's kernel guards: {"applied": [...], "missing": {...}}
        self.restarts = 0
        self._proc: subprocess.Popen | None = None
        self._fds: tuple = ()  # (write to the worker, read from the worker)
        self._stderr = None
        self._lock = threading.Lock()
        self._start()

    # --- worker management ------------------------------------------------------------------------------
    @property
    def pid(self) -> int | None:
        """The worker's process id (None when not running)."""
        return self._proc.pid if self._proc is not None and self._proc.poll() is None else None

    def _start(self) -> None:
        to_worker, from_parent = os.pipe()[::-1]  # (write end, read end)
        from_worker, to_parent = os.pipe()
        config = {"room": self.room, "memory_mb": self.memory_mb, "cpu_seconds": self.cpu_seconds,
                  "clamp": self.clamp, "fd_in": from_parent, "fd_out": to_parent}
        root = str(Path(__file__).resolve().parents[1])
        env = {k: v for k, v in os.environ.items() if k in WORKER_ENV}  # no API keys or tokens for programs
        env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", PYTHONDONTWRITEBYTECODE="1",
                   PYTHONPATH=os.pathsep.join(
                       [root] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
        self._stderr = tempfile.TemporaryFile()
        t = time.monotonic()
        self._fds = (to_worker, from_worker)
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-c", "import sys; from rewards.sandbox_worker import worker_main; "
                 "worker_main(sys.argv[1])", json.dumps(config)],
                stdin=subprocess.DEVNULL, stdout=self._stderr, stderr=self._stderr,
                pass_fds=(from_parent, to_parent), cwd=root, env=env, start_new_session=True)
        except OSError as err:
            self._kill()
            raise SandboxError(f"the reward sandbox worker could not be started: {err}") from None
        finally:
            os.close(from_parent)
            os.close(to_parent)
        try:
            ready = self._receive(time.monotonic() + self.startup_timeout)
        except _WorkerLost as err:
            tail = self._stderr_tail()
            self._kill()
            raise SandboxError(f"the reward sandbox worker failed to start: it {err}\n{tail}") from None
        self.startup_seconds = time.monotonic() - t
        self.confinement = ready.get("confinement") or {"applied": [], "missing": {"kernel guards": "not reported"}}
        if self.confinement["missing"]:
            self._refuse_weak_guard()

    def _refuse_weak_guard(self) -> None:
        """On a machine where the kernel cannot confine the worker: refuse, unless IARCS_WEAK_SANDBOX=1 (then warn
        once per process)."""
        missing = "; ".join(f"{k}: {v}" for k, v in self.confinement["missing"].items())
        if os.environ.get(WEAK_SANDBOX_ENV) != "1":
            self._kill()
            raise SandboxError(
                f"the reward sandbox cannot confine programs on this machine ({missing}); they would run behind "
                f"Python-level checks alone, which a determined program can get past. Use a Linux kernel with "
                f"Landlock and seccomp (and libseccomp installed), or set {WEAK_SANDBOX_ENV}=1 to run trusted "
                "programs anyway")
        if not _WEAK_WARNED:
            _WEAK_WARNED.append(True)
            print(f"warning: reward programs run with a weaker sandbox ({missing}; {WEAK_SANDBOX_ENV}=1)",
                  file=sys.stderr)

    def _stderr_tail(self, n: int = 2000) -> str:
        try:
            self._stderr.seek(0, os.SEEK_END)
            size = self._stderr.tell()
            self._stderr.seek(max(0, size - n))
            return self._stderr.read().decode(errors="replace")
        except (OSError, ValueError, AttributeError):
            return ""

    def _kill(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            if proc.poll() is None:
                proc.kill()
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                pass
        for fd in self._fds:
            try:
                os.close(fd)
            except OSError:
                pass
        self._fds = ()
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None

    def _receive(self, deadline: float) -> dict:
        fd = self._fds[1]
        try:
            header = _read_exact(fd, _HEADER.size, deadline)
            if header is not None:
                size = _HEADER.unpack(header)[0]
                if size > MAX_REPLY_BYTES:
                    self._kill()
                    raise _WorkerLost(f"sent a reply of {size} bytes (limit {MAX_REPLY_BYTES})")
                payload = _read_exact(fd, size, deadline)
                if payload is not None:
                    reply = json.loads(payload)
                    if not isinstance(reply, dict):
                        raise ValueError("reply is not an object")
                    return reply
        except TimeoutError:
            raise _WorkerLost("timed out") from None
        except ValueError as err:  # a garbled reply
            self._kill()
            raise _WorkerLost(f"sent an unreadable reply ({err})") from None
        try:
            code = self._proc.wait(5)
        except subprocess.TimeoutExpired:
            code = None
        raise _WorkerLost(_death_reason(code, self.cpu_seconds, self.memory_mb))

    def _request(self, msg: dict) -> dict:
        """Send one request and wait for its reply within the deadline; _WorkerLost otherwise (the worker
        is then killed and will restart on the next request)."""
        if self._proc is None or self._proc.poll() is not None:
            self._restart()
        try:
            _write_frame(self._fds[0], pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL))
            reply = self._receive(time.monotonic() + self.timeout)
        except (BrokenPipeError, _WorkerLost) as err:
            reason = str(err) if isinstance(err, _WorkerLost) else "had died"
            if reason == "timed out":
                reason = f"timed out after {self.timeout:g} s (the per-batch deadline)"
            self._kill()
            raise _WorkerLost(reason) from None
        if reply.get("restart"):
            self._kill()
        return reply

    def _restart(self) -> None:
        """Start a fresh worker and reload the active program (no smoke test: it passed before)."""
        self._kill()
        self.restarts += 1
        self._start()
        if self.code is not None:
            try:
                reply = self._request({"op": "load", "code": self.code, "smoke": False})
            except _WorkerLost as err:
                reply = {"ok": False, "message": str(err)}
            if not reply.get("ok"):
                self.code = None  # cannot happen for a program that loaded before, but never run a stale one

    # --- public API -------------------------------------------------------------------------------------
    def load(self, code: str) -> LoadResult:
        """Check, compile and smoke-test a program in the worker; it becomes active when this succeeds.
        On failure the previously loaded program stays active and ``message`` says what to fix."""
        return self._load(code, check=True)

    def _load(self, code: str, check: bool) -> LoadResult:
        """``load``; ``check=False`` skips the AST check (only for testing the worker's own defences)."""
        problems = check_program(code) if check else []
        if problems:
            return LoadResult(False, "The reward program was rejected by the static check:\n- "
                              + "\n- ".join(problems))
        with self._lock:
            try:
                reply = self._request({"op": "load", "code": code, "smoke": True})
            except _WorkerLost as err:
                return LoadResult(False, f"Loading the reward program failed: the sandbox worker {err}. Use "
                                  "vectorised tensor operations, no long loops or huge tensors.")
            if not reply.get("ok"):
                return LoadResult(False, "The reward program failed its smoke test on fixture scenes: "
                                  + str(reply.get("message", "unknown error")))
            self.code = code
            values = np.asarray(reply.get("values", []), dtype=np.float64)
            summary = (f"; values min {values.min():.3g}, mean {values.mean():.3g}, max {values.max():.3g}"
                       if values.size else "")
            note = f" ({reply['clipped']} values beyond +-{self.clamp:g} were clipped)" if reply.get("clipped") else ""
            return LoadResult(True, f"loaded; smoke test passed on {values.size} fixture scenes{summary}{note}")

    def score(self, batch, gradient: bool = False) -> ScoreResult:
        """Run the active program on a SceneBatch. On failure ``ok`` is False, ``values`` are zeros and
        ``message`` says why (error, timeout, crash); the program stays loaded. With ``gradient`` the worker
        also differentiates the values' sum with respect to the geometry (``ScoreResult.gradient``)."""
        b = batch.batch_size
        zeros = np.zeros(b, dtype=np.float64)
        shapes = {"translations": tuple(batch.translations.shape), "half_sizes": tuple(batch.half_sizes.shape),
                  "yaws": tuple(batch.yaws.shape)}
        no_gradient = {k: np.zeros(v) for k, v in shapes.items()} if gradient else None
        if self.code is None:
            return ScoreResult(zeros, False, "no reward program is loaded", gradient=no_gradient)
        t = time.monotonic()
        with self._lock:
            try:
                reply = self._request({"op": "score", "batch": describe_batch(batch), "gradient": gradient})
            except _WorkerLost as err:
                return ScoreResult(zeros, False, f"reward(scene) failed on a batch of {b} scenes: the sandbox "
                                   f"worker {err}; it was restarted", seconds=time.monotonic() - t,
                                   gradient=no_gradient)
        seconds = time.monotonic() - t
        output = str(reply.get("output", ""))[:MAX_PRINT_CHARS + 200]
        if not reply.get("ok"):
            return ScoreResult(zeros, False, str(reply.get("message", "unknown error"))[:4000], seconds=seconds,
                               output=output, gradient=no_gradient)
        try:
            values = np.asarray(reply["values"], dtype=np.float64).reshape(-1)
            grads = ({k: np.asarray(reply["gradient"][k], dtype=np.float64) for k in shapes} if gradient else None)
        except (KeyError, TypeError, ValueError):
            values, grads = np.zeros(0), None
        if values.shape != (b,) or (gradient and (grads is None or any(grads[k].shape != v
                                                                        for k, v in shapes.items()))):
            with self._lock:
                self._kill()  # the protocol cannot be trusted any more: start afresh next time
            return ScoreResult(zeros, False, f"the sandbox worker returned {values.size} values for {b} scenes"
                               + (" or a gradient of the wrong shape" if gradient else ""),
                               seconds=seconds, output=output, gradient=no_gradient)
        if grads is not None:  # never trust the worker
            grads = {k: np.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0) for k, g in grads.items()}
        values, extra_nonfinite, extra_clipped = _clamp(values, self.clamp)  # never trust the worker
        nonfinite = int(reply.get("nonfinite", 0)) + extra_nonfinite
        clipped = int(reply.get("clipped", 0)) + extra_clipped
        notes = []
        if nonfinite:
            notes.append(f"{nonfinite} of {b} values were NaN/inf (NaN -> 0, +-inf -> +-{self.clamp:g})")
        if clipped:
            notes.append(f"{clipped} of {b} values were beyond +-{self.clamp:g} and were clipped")
        return ScoreResult(values, True, "; ".join(notes), nonfinite, clipped, seconds, output, grads)

    def close(self) -> None:
        """Stop the worker (idempotent)."""
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.poll() is None:
            try:
                _write_frame(self._fds[0], pickle.dumps({"op": "exit"}))
                proc.wait(2)
            except (OSError, ValueError, IndexError, subprocess.TimeoutExpired):
                pass
        if hasattr(self, "_proc"):
            self._kill()

    def __enter__(self) -> "RewardSandbox":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 -- interpreter shutdown
            pass

    def __repr__(self) -> str:
        return (f"RewardSandbox(room={self.room!r}, timeout={self.timeout:g}, memory_mb={self.memory_mb}, "
                f"pid={self.pid}, program={'yes' if self.code else 'none'})")


class SandboxedReward:
    """A reward callable ``batch -> tensor (B,)`` running a program in a :class:`RewardSandbox`.

    ``code_or_sandbox`` is program source (a sandbox is created and owned, extra keyword arguments go to
    it; a program that does not load raises ValueError with the sandbox's message) or a sandbox with a
    program loaded. The last good program stays active across :meth:`load` failures.

    When a batch fails at run time (exception, timeout, crash, wrong output) the call returns **zeros**
    for that batch: a constant term carries no preference between scenes (and no signal after per-floor
    advantage normalisation), whereas reusing stale values would reward scenes for what other scenes
    did. The failure is counted and its message kept (``messages``, :meth:`take_messages`) for reflection.
    """

    def __init__(self, code_or_sandbox, room: str = "bedroom", **sandbox_kwargs):
        if isinstance(code_or_sandbox, RewardSandbox):
            self.sandbox, self._owns = code_or_sandbox, False
        else:
            problems = check_program(code_or_sandbox)
            if problems:  # refuse before paying for a worker
                raise ValueError("The reward program was rejected by the static check:\n- " + "\n- ".join(problems))
            self.sandbox, self._owns = RewardSandbox(room=room, **sandbox_kwargs), True
            result = self.sandbox.load(code_or_sandbox)
            if not result.ok:
                self.sandbox.close()
                raise ValueError(result.message)
        if self.sandbox.code is None:
            raise ValueError("the sandbox has no reward program loaded; call sandbox.load(code) first")
        self.calls = 0
        self.failures = 0
        self.load_failures = 0
        self.nonfinite = 0
        self.seconds = 0.0
        self.last_message = ""
        self.messages: deque[str] = deque(maxlen=20)

    @property
    def code(self) -> str:
        """Source of the active program."""
        return self.sandbox.code

    def _record(self, message: str) -> None:
        self.last_message = message
        self.messages.append(message)

    def _score(self, batch, gradient: bool) -> ScoreResult:
        result = self.sandbox.score(batch, gradient=gradient)
        self.calls += 1
        self.seconds += result.seconds
        self.nonfinite += result.nonfinite
        if not result.ok:
            self.failures += 1
            self._record(f"batch {self.calls}: {result.message}")
        elif result.message:
            self._record(f"batch {self.calls}: {result.message}")
        return result

    def __call__(self, batch) -> torch.Tensor:
        result = self._score(batch, gradient=False)
        return torch.as_tensor(result.values, dtype=torch.float32, device=batch.labels.device)

    def gradient(self, batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(values (B,), their sum's gradient with respect to the batch's geometry: ``translations``,
        ``half_sizes``, ``yaws``), zeros where the batch fails (recorded as in a call)."""
        result = self._score(batch, gradient=True)
        as_tensor = lambda a: torch.as_tensor(a, dtype=torch.float32, device=batch.labels.device)  # noqa: E731
        return as_tensor(result.values), {k: as_tensor(g) for k, g in result.gradient.items()}

    def load(self, code: str) -> LoadResult:
        """Swap in a new program; on failure the current one stays and the failure is recorded."""
        result = self.sandbox.load(code)
        if not result.ok:
            self.load_failures += 1
            self._record(f"load: {result.message}")
        return result

    def take_messages(self) -> list[str]:
        """The recorded messages since the last call (for ``ReflectionContext.sandbox_messages``)."""
        out = list(self.messages)
        self.messages.clear()
        return out

    def stats(self) -> dict:
        """Counters: calls, failures, load failures, NaN/inf values replaced, mean seconds per call."""
        return {"calls": self.calls, "failures": self.failures, "load_failures": self.load_failures,
                "nonfinite": self.nonfinite, "mean_seconds": self.seconds / max(1, self.calls),
                "startup_seconds": self.sandbox.startup_seconds, "restarts": self.sandbox.restarts}

    def close(self) -> None:
        """Close the sandbox when this object created it."""
        if self._owns:
            self.sandbox.close()

    def __enter__(self) -> "SandboxedReward":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["ALLOWED_IMPORTS", "DEFAULT_CLAMP", "DEFAULT_MEMORY_MB", "LoadResult", "RewardSandbox", "SandboxError",
           "SandboxedReward", "ScoreResult", "check_program", "describe_batch"]

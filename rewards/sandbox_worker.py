"""Layer 2 of the reward sandbox (:mod:`rewards.sandbox`): the worker process that runs one reward program at a
time, and the wire format it speaks with the parent.

The worker (``python -c``, :func:`worker_main`) limits its own address space, CPU time per request, file size and
core dumps, has 1 torch thread, gives programs a few safe builtins and read-only ``torch``/``math`` proxies that
refuse submodules outside an allow-list, installs an audit hook (sockets, subprocesses, ctypes, and while a program
runs, file writes and reads outside the Python installation), and then confines itself in the kernel for good
(:func:`rewards.confine.confine`) before it reads the first program. One request per message over two pipes:
parent -> worker a pickled dict (a plain-numpy description of the SceneBatch), worker -> parent a JSON dict.
"""

from __future__ import annotations

import json
import os
import pickle
import re
import select
import signal
import struct
import sys
import time
from pathlib import Path

import numpy as np
import torch

from rewards.program_check import ALLOWED_IMPORTS, FORBIDDEN_ATTRIBUTES

#: Second line of defence in the worker's module proxies: names of module attributes refused at run time
#: (on top of FORBIDDEN_ATTRIBUTES, private names and submodules outside ALLOWED_IMPORTS).
PROXY_DENY = re.compile(r"(?i)file|load|save|import|serial|script|compil|jit|thread|process|librar|hook|environ"
                        r"|^set_|debug|anomaly")
#: Builtins available to programs (``print`` is replaced by a bounded capture).
SAFE_BUILTINS = (
    "abs", "all", "any", "bool", "callable", "chr", "dict", "divmod", "enumerate", "filter", "float",
    "frozenset", "hash", "int", "isinstance", "iter", "len", "list", "map", "max", "min", "next", "ord",
    "pow", "range", "repr", "reversed", "round", "set", "slice", "sorted", "str", "sum", "tuple", "zip",
    "ArithmeticError", "AssertionError", "Exception", "IndexError", "KeyError", "LookupError",
    "NotImplementedError", "RuntimeError", "StopIteration", "TypeError", "ValueError", "ZeroDivisionError",
)#: Captured ``print`` output kept per request (characters).
MAX_PRINT_CHARS = 4000
#: Number of generated fixture scenes for the smoke test (plus one empty room).
FIXTURE_SCENES = 6

# ------------------------------------------------------------------------------------------------------
# Wire format
# ------------------------------------------------------------------------------------------------------
_HEADER = struct.Struct(">Q")


def describe_batch(batch) -> dict:
    """A plain-numpy description of a SceneBatch (what goes to the worker)."""
    return {
        "room": batch.spec.name,
        "labels": batch.labels.detach().cpu().numpy().astype(np.int64),
        "translations": batch.translations.detach().cpu().numpy().astype(np.float32),
        "half_sizes": batch.half_sizes.detach().cpu().numpy().astype(np.float32),
        "yaws": batch.yaws.detach().cpu().numpy().astype(np.float32),
        "floors": [np.asarray(f.vertices, dtype=np.float64) for f in batch.floors],
        "ids": [str(i) for i in batch.ids],
    }


#: The geometry a reward's gradient is taken with respect to (``score`` with ``gradient``).
GEOMETRY = ("translations", "half_sizes", "yaws")


def _rebuild_batch(desc: dict, requires_grad: bool = False):
    """The SceneBatch of a description; with ``requires_grad`` its geometry tensors are autograd leaves
    (``batch.translations`` etc.), so a program's value can be differentiated with respect to them."""
    from iarcs_env.floorplan import FloorPlan
    from iarcs_env.rooms import get_room
    from iarcs_env.scene import SceneBatch

    geometry = [torch.from_numpy(desc[k]).requires_grad_(requires_grad) for k in GEOMETRY]
    return SceneBatch(get_room(desc["room"]), torch.from_numpy(desc["labels"]), *geometry,
                      [FloorPlan(np.asarray(v)) for v in desc["floors"]], list(desc["ids"]))


def _write_frame(fd: int, payload: bytes) -> None:
    data = _HEADER.pack(len(payload)) + payload
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _read_exact(fd: int, n: int, deadline: float | None) -> bytes | None:
    """Read n bytes; None on EOF; TimeoutError past the deadline."""
    chunks, got = [], 0
    while got < n:
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise TimeoutError
        chunk = os.read(fd, min(n - got, 1 << 20))
        if not chunk:
            return None
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


# ------------------------------------------------------------------------------------------------------
# Layer 2: the worker process
# ------------------------------------------------------------------------------------------------------
class _BadResult(Exception):
    pass


class _Printer:
    """A bounded ``print`` for programs: keeps the first MAX_PRINT_CHARS characters, counts the rest."""

    def __init__(self):
        self.reset()

    def reset(self):
        self.parts, self.kept, self.dropped = [], 0, 0

    def __call__(self, *args, sep=" ", end="\n", **kwargs):
        if self.kept >= MAX_PRINT_CHARS:
            self.dropped += 1
            return
        text = str(sep).join(str(a)[:MAX_PRINT_CHARS] for a in args[:100]) + str(end)
        text = text[:MAX_PRINT_CHARS - self.kept]
        self.parts.append(text)
        self.kept += len(text)

    def text(self) -> str:
        out = "".join(self.parts)
        if self.dropped:
            out += f"\n... ({self.dropped} more print calls dropped)"
        return out


def _module_proxy(module, name: str, allowed_children: dict):
    """A read-only view of a module that refuses private names, forbidden attributes and submodules
    outside ALLOWED_IMPORTS (``torch.os``, ``torch.serialization``...)."""
    import types

    class SandboxedModule:
        __slots__ = ()

        def __getattr__(self, attr):
            if attr.startswith("_") or attr in FORBIDDEN_ATTRIBUTES or PROXY_DENY.search(attr):
                raise AttributeError(f"{name}.{attr} is not available to reward programs")
            value = getattr(module, attr)
            if isinstance(value, types.ModuleType):
                child = allowed_children.get(f"{name}.{attr}")
                if child is None:
                    raise AttributeError(f"{name}.{attr} is not available to reward programs")
                return child
            return value

        def __setattr__(self, attr, value):
            raise AttributeError(f"{name} is read-only in reward programs")

        __delattr__ = __setattr__

        def __repr__(self):
            return f"<module {name!r} (sandboxed)>"

    return SandboxedModule()


def _safe_modules() -> dict:
    import importlib

    proxies: dict = {}
    for full in sorted(ALLOWED_IMPORTS, key=lambda n: -n.count(".")):  # children first
        children = {k: v for k, v in proxies.items() if k.rsplit(".", 1)[0] == full}
        proxies[full] = _module_proxy(importlib.import_module(full), full, children)
    return proxies


def _audit_hook_factory(state: dict, roots: tuple):
    """Refuse network, subprocesses and ctypes always; while a program runs, also file writes, reads
    outside ``roots`` and filesystem changes."""
    always = ("socket.", "subprocess.", "os.system", "os.exec", "os.spawn", "os.posix_spawn", "os.fork",
              "os.forkpty", "pty.", "urllib.", "http.", "ftplib.", "smtplib.", "webbrowser.", "os.kill",
              "os.killpg", "signal.pthread_kill")
    running = ("ctypes.", "os.remove", "os.unlink", "os.rename", "os.replace", "os.mkdir", "os.rmdir",
               "os.chmod", "os.chown", "os.truncate", "os.symlink", "os.link", "os.utime", "os.chdir",
               "os.putenv", "os.unsetenv", "shutil.", "sys.settrace", "sys.setprofile", "tempfile.", "mmap.")
    write_flags = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND

    def hook(event, args):
        if event.startswith(always) or state["running"] and event.startswith(running):
            raise PermissionError(f"{event} is not allowed in the reward sandbox")
        if event == "open" and state["running"]:
            path, mode, flags = (tuple(args) + (None, None, 0))[:3]
            if isinstance(path, int):
                return
            writes = any(c in mode for c in "wax+") if isinstance(mode, str) else bool((flags or 0) & write_flags)
            real = os.path.realpath(os.fsdecode(path))
            if writes or not any(real == r or real.startswith(r + os.sep) for r in roots):
                raise PermissionError(f"opening {os.fsdecode(path)!r} is not allowed in the reward sandbox")

    return hook


def _format_error(err: BaseException, code_lines: list[str]) -> str:
    """``reward(scene) raised X: msg`` with the program's own lines of the traceback."""
    import traceback

    where = []
    for frame in traceback.extract_tb(err.__traceback__):
        if frame.filename == "<reward>" and frame.lineno and frame.lineno <= len(code_lines):
            where.append(f"  line {frame.lineno}: {code_lines[frame.lineno - 1].strip()[:120]}")
    msg = str(err)[:500]
    text = f"{type(err).__name__}: {msg}" if msg else type(err).__name__
    return text + ("\n" + "\n".join(where[-5:]) if where else "")


def _to_values(out, batch_size: int) -> np.ndarray:
    """The program's return value as a float64 array (B,); _BadResult with an explanation otherwise."""
    want = f"return a float tensor of shape (B,) = ({batch_size},), one value per scene"
    if out is None:
        raise _BadResult(f"reward(scene) returned None (missing `return`?); {want}")
    if isinstance(out, (bool, int, float)):
        raise _BadResult(f"reward(scene) returned a single number; {want}")
    if isinstance(out, (list, tuple)):
        if len(out) != batch_size:
            raise _BadResult(f"reward(scene) returned a {type(out).__name__} of length {len(out)}; {want}")
        try:
            out = torch.as_tensor([float(v) for v in out], dtype=torch.float64)
        except (TypeError, ValueError) as err:
            raise _BadResult(f"reward(scene) returned a {type(out).__name__} with non-numbers ({err}); {want}")
    if not isinstance(out, torch.Tensor):
        raise _BadResult(f"reward(scene) returned a {type(out).__name__}; {want}")
    shape = tuple(out.shape)
    if shape != (batch_size,):
        hint = " (use .squeeze(-1) or reduce over objects)" if shape[:1] == (batch_size,) else ""
        raise _BadResult(f"reward(scene) returned a tensor of shape {shape}{hint}; {want}")
    if out.is_complex() or not (out.dtype.is_floating_point or out.dtype in (torch.bool, torch.int64, torch.int32,
                                                                             torch.int16, torch.int8, torch.uint8)):
        raise _BadResult(f"reward(scene) returned a tensor of dtype {out.dtype}; {want}")
    return out.detach().to("cpu", torch.float64).numpy().copy()


def _clamp(values: np.ndarray, bound: float) -> tuple[np.ndarray, int, int]:
    finite = np.isfinite(values)
    nonfinite = int((~finite).sum())
    clipped = int((np.abs(values[finite]) > bound).sum())
    values = np.nan_to_num(values, nan=0.0, posinf=bound, neginf=-bound)
    return np.clip(values, -bound, bound), nonfinite, clipped


def _is_oom(err: BaseException) -> bool:
    return isinstance(err, MemoryError) or (isinstance(err, RuntimeError) and "allocate" in str(err))


def worker_main(config_json: str) -> None:
    """Entry point of the worker process (``python -c``); see the module docstring."""
    import resource

    t0 = time.monotonic()
    config = json.loads(config_json)
    proto_in, proto_out = int(config["fd_in"]), int(config["fd_out"])  # stdout/stderr go to a bounded file
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past RLIMIT_FSIZE fail instead of killing

    def lower_limit(kind, value):
        hard = resource.getrlimit(kind)[1]
        value = value if hard == resource.RLIM_INFINITY else min(value, hard)
        resource.setrlimit(kind, (value, value))

    lower_limit(resource.RLIMIT_AS, int(config["memory_mb"]) << 20)
    lower_limit(resource.RLIMIT_CORE, 0)
    lower_limit(resource.RLIMIT_FSIZE, 1 << 20)
    cpu_hard = resource.getrlimit(resource.RLIMIT_CPU)[1]

    torch.set_num_threads(1)
    from iarcs_env.datasets.procedural import generate_layouts
    from iarcs_env.floorplan import FloorPlan
    from iarcs_env.scene import Layout, SceneBatch
    from rewards.scene_api import Scene

    layouts = generate_layouts(config["room"], FIXTURE_SCENES, seed=0)
    first = layouts[0]
    empty = Layout(first.room_type, first.floor, [], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), id="empty")
    square = Layout(first.room_type, FloorPlan.from_vertices([(-1.5, -1.5), (1.5, -1.5), (1.5, 1.5), (-1.5, 1.5)]),
                    [], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), id="empty-square")
    fixtures = SceneBatch.from_layouts(layouts + [empty, square])

    printer = _Printer()
    modules = _safe_modules()

    def restricted_import(name, globals=None, locals=None, fromlist=(), level=0):
        if level or name not in modules:
            raise ImportError(f"import of {name!r} is not allowed in reward programs (only math and torch)")
        return modules[name] if fromlist else modules[name.split(".")[0]]

    import builtins

    safe_builtins = {k: getattr(builtins, k) for k in SAFE_BUILTINS}
    safe_builtins.update(print=printer, __import__=restricted_import)

    from rewards.confine import confine

    confinement = confine(Path(__file__).resolve().parents[1])  # the kernel's guards, for good, before any program
    state = {"running": False, "phase": "reward(scene)"}
    roots = {os.path.realpath(p) for p in (sys.prefix, sys.base_prefix, sys.exec_prefix)}
    roots |= {os.path.realpath(p) for p in sys.path if p and os.path.isdir(p)}
    sys.addaudithook(_audit_hook_factory(state, tuple(sorted(roots))))

    cpu_seconds = int(config["cpu_seconds"])
    clamp = float(config["clamp"])
    program = None  # (reward function, source lines)

    def run(fn, batch, gradient: bool = False) -> dict:
        """Call the program on a batch; the reply dict. With ``gradient`` the reply also holds the gradient of
        the values' sum with respect to the batch's geometry (zero for scenes whose value was NaN/inf or
        clipped, and where the program's value does not depend on the geometry)."""
        scene = Scene(batch)
        state["running"] = True
        try:
            out = fn(scene)
            values = _to_values(out, batch.batch_size)
            leaves = [getattr(batch, k) for k in GEOMETRY]
            if gradient and isinstance(out, torch.Tensor) and out.requires_grad:
                grads = torch.autograd.grad(out.float().sum(), leaves, allow_unused=True)
            else:
                grads = (None,) * len(leaves)
        finally:
            state["running"] = False
        kept = np.isfinite(values) & (np.abs(values) <= clamp)
        values, nonfinite, clipped = _clamp(values, clamp)
        reply = {"ok": True, "values": values.tolist(), "nonfinite": nonfinite, "clipped": clipped}
        if gradient:
            reply["gradient"] = {}
            for key, leaf, g in zip(GEOMETRY, leaves, grads):
                g = (torch.zeros_like(leaf) if g is None
                     else torch.nan_to_num(g.detach(), nan=0.0, posinf=0.0, neginf=0.0))
                g[torch.from_numpy(~kept)] = 0
                reply["gradient"][key] = g.to(torch.float64).numpy().tolist()
        return reply

    def handle(msg: dict) -> dict:
        nonlocal program
        op = msg.get("op")
        if op == "load":
            glb = {"__builtins__": dict(safe_builtins), "__name__": "reward_program",
                   "torch": modules["torch"], "math": modules["math"]}
            state.update(running=True, phase="loading the program")
            try:  # the one exec of generated code: inside the limited worker, with restricted builtins
                exec(compile(msg["code"], "<reward>", "exec"), glb)
            finally:
                state["running"] = False
            state["phase"] = "reward(scene)"
            fn = glb.get("reward")
            if not callable(fn):
                return {"ok": False, "message": "the program does not define a function `reward(scene)`"}
            reply = {"ok": True, "values": []}
            if msg.get("smoke", True):
                reply = run(fn, fixtures)
                if reply["nonfinite"]:
                    return {"ok": False, "message": (
                        f"the smoke test on {fixtures.batch_size} fixture scenes (including empty rooms) gave "
                        f"{reply['nonfinite']} NaN/inf values; guard divisions, logs and empty masks so every "
                        "scene gets a finite value")}
            program = (fn, msg["code"].splitlines())
            return reply
        if op == "score":
            if program is None:
                return {"ok": False, "message": "no reward program is loaded in the worker"}
            gradient = bool(msg.get("gradient", False))
            return run(program[0], _rebuild_batch(msg["batch"], gradient), gradient)
        return {"ok": False, "message": f"unknown request {op!r}"}

    _write_frame(proto_out, json.dumps({"ok": True, "ready": True, "pid": os.getpid(), "confinement": confinement,
                                        "startup": time.monotonic() - t0}).encode())
    while True:
        header = _read_exact(proto_in, _HEADER.size, None)
        if header is None:
            return
        payload = _read_exact(proto_in, _HEADER.unpack(header)[0], None)
        if payload is None:
            return
        msg = pickle.loads(payload)
        if msg.get("op") == "exit":
            return
        used = resource.getrusage(resource.RUSAGE_SELF)
        soft = int(used.ru_utime + used.ru_stime) + 1 + cpu_seconds  # this request's CPU budget
        resource.setrlimit(resource.RLIMIT_CPU, (soft if cpu_hard == resource.RLIM_INFINITY else min(soft, cpu_hard),
                                                 cpu_hard))
        printer.reset()
        t = time.monotonic()
        fatal = False
        lines = msg["code"].splitlines() if msg.get("op") == "load" else (program[1] if program else [])
        try:
            reply = handle(msg)
        except _BadResult as err:
            reply = {"ok": False, "message": str(err)}
        except BaseException as err:  # noqa: BLE001 -- everything a program raises is reported
            fatal = _is_oom(err)
            reply = {"ok": False, "message": f"{state['phase']} raised " + _format_error(err, lines)}
            state["phase"] = "reward(scene)"
            if fatal:
                reply["message"] += f"\n(the memory limit is {config['memory_mb']} MB; the worker was restarted)"
        reply["compute_seconds"] = time.monotonic() - t
        reply["output"] = printer.text()
        reply["restart"] = fatal
        _write_frame(proto_out, json.dumps(reply).encode())
        if fatal:
            os._exit(3)

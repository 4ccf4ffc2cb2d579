"""Sandbox for generated reward programs (LLM- or planner-written ``def reward(scene)``).

A reward program never runs with plain ``exec`` in the training process. It goes through three layers:

1. :func:`check_program` reads its AST and refuses, with messages meant to be sent back to the LLM:
   imports other than ``math``/``torch``, any name or attribute starting with ``_`` (a bare ``_`` is
   allowed), the builtins that reach outside (open, eval, exec, getattr, globals, ...), attributes through
   which torch or numpy reach the system or files (``torch.os``, ``torch.load``, ``torch.hub``,
   ``torch.utils``, ``x.numpy()``, ``a.tofile``, frame and generator internals such as ``gi_frame``,
   ``str.format`` ...), attribute assignment, classes, ``global``, and top-level statements other than
   imports, constant assignments and function definitions (so loading runs nothing but definitions).
2. The program runs in a long-lived worker process (``sys.executable``) that limits its own address
   space (``memory_mb``), CPU time per request (``cpu_seconds``), file size (1 MB: no large writes) and
   core dumps, has 1 torch thread, sees only a few safe builtins, gets read-only ``torch``/``math``
   proxies that refuse submodules outside an allow-list (``torch.os``, ``torch.serialization``, ...),
   and installs an audit hook that refuses sockets, subprocesses, ``os.system``/exec/fork and ctypes,
   and, while a program runs, any file write and any read outside the Python installation.
3. The parent enforces a wall-clock deadline per request (kill and restart the worker, report
   "timed out after X s"), reads replies as length-prefixed JSON (never pickle: a subverted worker cannot
   run code in the trainer) of bounded size, and re-checks and clamps the values.

One request per message over two dedicated pipes (the worker's stdout and stderr go to a size-limited
temporary file): parent -> worker is a pickled dict (a plain-numpy description of the
:class:`~iarcs_env.scene.SceneBatch`), worker -> parent a JSON dict. :class:`RewardSandbox` owns one
worker; :class:`SandboxedReward` is the callable ``batch -> tensor (B,)`` for
:class:`~rewards.composite.CompositeReward`.
"""

from __future__ import annotations

import ast
import json
import math
import os
import pickle
import re
import select
import signal
import struct
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

# ------------------------------------------------------------------------------------------------------
# Limits and lists
# ------------------------------------------------------------------------------------------------------
#: Longest program source accepted (characters).
MAX_CODE_CHARS = 50_000
#: Modules a program may import (``torch`` and ``math`` are also pre-bound globals).
ALLOWED_IMPORTS = ("math", "torch", "torch.nn", "torch.nn.functional", "torch.linalg", "torch.special",
                   "torch.fft")
#: Builtins a program may not name at all.
FORBIDDEN_NAMES = frozenset({
    "open", "eval", "exec", "compile", "getattr", "setattr", "delattr", "hasattr", "globals", "locals",
    "vars", "dir", "input", "breakpoint", "exit", "quit", "help", "type", "object", "super", "memoryview",
    "classmethod", "staticmethod", "property", "copyright", "credits", "license",
})
#: Attribute names refused on any object: module escapes through torch (``torch.os``, ``torch.sys``...),
#: file and network access, compilation, thread settings, numpy/ctypes views, frame internals, format
#: strings (``"{0.__class__}".format(x)`` reads attributes).
FORBIDDEN_ATTRIBUTES = frozenset({
    # modules reachable as torch attributes
    "os", "sys", "subprocess", "builtins", "importlib", "ctypes", "glob", "inspect", "platform", "signal",
    "threading", "types", "socket", "shutil", "pathlib", "io", "pickle", "multiprocessing", "distributed",
    "serialization", "hub", "utils", "cpp_extension", "jit", "fx", "package", "onnx", "library", "ops",
    "compiler", "export", "cpp", "testing", "profiler", "monitor", "storage", "futures",
    "backends", "overrides", "warnings", "torch", "model_zoo",
    # file, code and process access
    "load", "save", "load_library", "load_inline", "from_file", "tofile", "fromfile", "dump", "dumps",
    "loads", "numpy", "untyped_storage", "share_memory_", "filename", "compile", "system", "popen",
    "environ", "spawn", "execv", "execve", "fork", "urlopen", "download_url_to_file",
    "load_state_dict_from_url", "init_process_group",
    # process-wide torch settings (the worker is shared by later programs)
    "set_num_threads", "set_num_interop_threads", "set_default_dtype", "set_default_device",
    "set_default_tensor_type", "set_flush_denormal",
    # torch classes and functions that read, write or compile files and code
    "PyTorchFileReader", "PyTorchFileWriter", "import_ir_module", "import_ir_module_from_buffer", "get_file_path",
    "CompilationUnit", "ScriptModule", "ScriptFunction", "ScriptModuleSerializer", "SerializationStorageContext",
    "DeserializationStorageContext", "prepare_multiprocessing_environment", "FileCheck", "np",
    # introspection
    "format", "format_map", "mro", "with_traceback",
})
#: Second line of defence in the worker's module proxies: names of module attributes refused at run time
#: (on top of FORBIDDEN_ATTRIBUTES, private names and submodules outside ALLOWED_IMPORTS).
PROXY_DENY = re.compile(r"(?i)file|load|save|import|serial|script|compil|jit|thread|process|librar|hook|environ"
                        r"|^set_|debug|anomaly")
#: Attribute prefixes of frames, code objects, generators, coroutines and tracebacks.
FORBIDDEN_ATTRIBUTE_PREFIXES = ("f_", "gi_", "cr_", "ag_", "tb_", "co_", "im_", "func_")
#: Builtins available to programs (``print`` is replaced by a bounded capture).
SAFE_BUILTINS = (
    "abs", "all", "any", "bool", "callable", "chr", "dict", "divmod", "enumerate", "filter", "float",
    "frozenset", "hash", "int", "isinstance", "iter", "len", "list", "map", "max", "min", "next", "ord",
    "pow", "range", "repr", "reversed", "round", "set", "slice", "sorted", "str", "sum", "tuple", "zip",
    "ArithmeticError", "AssertionError", "Exception", "IndexError", "KeyError", "LookupError",
    "NotImplementedError", "RuntimeError", "StopIteration", "TypeError", "ValueError", "ZeroDivisionError",
)
#: Default address-space limit of the worker (MB). Importing torch, numpy, scipy, shapely and the scene
#: code with one thread maps about 0.7 GB (VmPeak measured ~700 MB; 600 MB already fails to import
#: scipy), so 2 GB leaves ~1.3 GB for a program: orders of magnitude more than 32 bedrooms need.
DEFAULT_MEMORY_MB = 2048
#: Values are clamped to [-CLAMP, CLAMP]; NaN becomes 0 and +-inf +-CLAMP.
DEFAULT_CLAMP = 10.0
#: Largest worker reply read by the parent (bytes), and captured ``print`` output kept per request.
MAX_REPLY_BYTES = 4 << 20
MAX_PRINT_CHARS = 4000
#: The only environment variables the worker inherits (the parent's may hold API keys a program could print).
WORKER_ENV = frozenset({"PATH", "LANG", "LC_ALL", "LC_CTYPE", "TZ", "PYTHONHASHSEED"})
#: Number of generated fixture scenes for the smoke test (plus one empty room).
FIXTURE_SCENES = 6


# ------------------------------------------------------------------------------------------------------
# Layer 1: the AST check
# ------------------------------------------------------------------------------------------------------
_FRIENDLY = {
    "open": "reward programs cannot read or write files",
    "eval": "reward programs cannot run code from strings",
    "exec": "reward programs cannot run code from strings",
    "compile": "reward programs cannot compile code",
    "getattr": "use plain attribute access (scene.position)",
    "setattr": "reward programs cannot set attributes",
    "delattr": "reward programs cannot delete attributes",
    "globals": "reward programs cannot inspect their namespace",
    "locals": "reward programs cannot inspect their namespace",
    "vars": "reward programs cannot inspect objects",
    "input": "reward programs cannot read input",
    "breakpoint": "reward programs cannot start a debugger",
    "exit": "return a value from reward(scene) instead",
    "quit": "return a value from reward(scene) instead",
}


def _snippet(code_lines: list[str], lineno: int | None) -> str:
    if not lineno or lineno > len(code_lines):
        return ""
    text = code_lines[lineno - 1].strip()
    return f" -> `{text[:100]}`" if text else ""


def _is_constant_expr(node: ast.AST) -> bool:
    """Literals, containers, arithmetic, names, ``math.x`` and ``math.f(...)`` calls."""
    ok = (ast.Constant, ast.Tuple, ast.List, ast.Set, ast.Dict, ast.UnaryOp, ast.BinOp, ast.BoolOp,
          ast.Compare, ast.IfExp, ast.Name, ast.Load, ast.operator, ast.unaryop, ast.cmpop, ast.boolop,
          ast.Attribute, ast.Call, ast.keyword)
    for n in ast.walk(node):
        if not isinstance(n, ok):
            return False
        if isinstance(n, ast.Attribute) and not (isinstance(n.value, ast.Name) and n.value.id == "math"):
            return False
        if isinstance(n, ast.Call) and not (isinstance(n.func, ast.Attribute) and isinstance(n.func.value, ast.Name)
                                            and n.func.value.id == "math"):
            return False
    return True


def _check_import(node: ast.AST, problems: list) -> None:
    allowed = "reward programs may only import math and torch (both are already available without importing)"
    if isinstance(node, ast.Import):
        for alias in node.names:
            if alias.name not in ALLOWED_IMPORTS:
                problems.append((node.lineno, f"`import {alias.name}` is not allowed: {allowed}"))
    else:
        mod = node.module or ""
        if node.level or mod not in ALLOWED_IMPORTS:
            problems.append((node.lineno, f"`from {'.' * node.level}{mod} import ...` is not allowed: {allowed}"))
        for alias in node.names:
            if alias.name == "*":
                problems.append((node.lineno, "`import *` is not allowed; import the names you use"))
            elif alias.name in FORBIDDEN_ATTRIBUTES:
                problems.append((node.lineno, f"`{mod}.{alias.name}` is not available to reward programs"))


def check_program(code: str) -> list[str]:
    """Problems with a reward program's source (human-readable, one per item); empty when it may run.

    Checks the syntax, the imports (math and torch only), that nothing starts with ``_`` (a bare ``_``
    is fine), forbidden builtins and attributes, and that the top level holds only imports, constant
    assignments (``MAX_HEIGHT = 1.0``) and function definitions including ``def reward(scene)``.
    """
    if not isinstance(code, str):
        return [f"the reward program must be Python source text, got {type(code).__name__}"]
    if len(code) > MAX_CODE_CHARS:
        return [f"the reward program is {len(code)} characters long; keep it under {MAX_CODE_CHARS}"]
    if not code.strip():
        return ["the reward program is empty; define `def reward(scene):` returning a tensor of shape (B,)"]
    lines = code.splitlines()
    try:
        tree = ast.parse(code, filename="<reward>")
    except SyntaxError as err:
        return [f"line {err.lineno}: syntax error: {err.msg}{_snippet(lines, err.lineno)}"]
    except (RecursionError, MemoryError, ValueError) as err:
        return [f"the reward program cannot be parsed ({type(err).__name__}: {str(err) or 'nested too deeply'}); "
                "write simpler, less deeply nested expressions"]

    problems: list[tuple[int, str]] = []
    # --- the top level: definitions only
    reward_defs = []
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom, ast.FunctionDef)):
            if isinstance(node, ast.FunctionDef) and node.name == "reward":
                reward_defs.append(node)
            continue
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            continue  # docstring
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names_only = all(isinstance(n, (ast.Name, ast.Tuple, ast.List, ast.Store))
                             for t in targets for n in ast.walk(t))
            if names_only and (node.value is None or _is_constant_expr(node.value)):
                continue
            problems.append((node.lineno, "top-level assignments must be constants (numbers, strings, tuples or "
                             "lists of them, arithmetic, math.pi, math.radians(30)); compute tensors inside "
                             "reward(scene)"))
            continue
        what = type(node).__name__.lower()
        problems.append((node.lineno, f"top-level `{what}` statements are not allowed: at the top level only "
                         "imports, constant assignments and function definitions may appear; put the work "
                         "inside reward(scene)"))
    if not reward_defs:
        problems.append((1, "no `def reward(scene):` at the top level; define it and return a float tensor of "
                         "shape (B,), one value per scene"))
    else:
        args = reward_defs[-1].args
        positional = args.posonlyargs + args.args
        required = len(positional) - len(args.defaults)
        if not positional or required != 1 or args.kwonlyargs and len(args.kw_defaults) != len(args.kwonlyargs):
            problems.append((reward_defs[-1].lineno, "reward must take exactly one argument: `def reward(scene):`"))

    # --- every node
    for node in ast.walk(tree):
        line = getattr(node, "lineno", 1)
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            _check_import(node, problems)
        elif isinstance(node, ast.ClassDef):
            problems.append((line, "class definitions are not allowed; use functions"))
        elif isinstance(node, (ast.AsyncFunctionDef, ast.Await, ast.AsyncFor, ast.AsyncWith)):
            problems.append((line, "async code is not allowed"))
        elif isinstance(node, ast.MatchClass):
            problems.append((line, "class patterns (`case C(...)`) are not allowed: they read attributes, private "
                             "ones included; compare values with if/elif or match literals"))
        elif isinstance(node, (ast.Global, ast.Nonlocal)):
            problems.append((line, "`global`/`nonlocal` are not allowed: reward programs must be stateless"))
        elif isinstance(node, ast.Name) and node.id in FORBIDDEN_NAMES:
            why = _FRIENDLY.get(node.id, "it is not available to reward programs")
            problems.append((line, f"`{node.id}` is not allowed: {why}"))
        elif isinstance(node, ast.Attribute):
            attr = node.attr
            if attr in ("format", "format_map"):
                problems.append((line, f"`.{attr}` is not allowed (it can read attributes); use f-strings"))
            elif attr in FORBIDDEN_ATTRIBUTES or attr.startswith(FORBIDDEN_ATTRIBUTE_PREFIXES):
                problems.append((line, f"attribute `.{attr}` is not allowed in reward programs (no file, process, "
                                 "network or interpreter access; use the Scene API and torch tensor operations)"))
            if isinstance(node.ctx, (ast.Store, ast.Del)) and not attr.startswith("_"):
                problems.append((line, f"assigning to attributes (`.{attr} = ...`) is not allowed; use local "
                                 "variables"))
        # names starting with "_" in any field: variables, attributes, arguments, keywords, aliases
        for key in ("id", "attr", "arg", "name", "asname"):
            value = getattr(node, key, None)
            if isinstance(value, str) and value.startswith("_") and value != "_":
                problems.append((line, f"`{value}`: names and attributes starting with '_' are not allowed "
                                 "(rename private helpers without the underscore)"))
    # order, deduplicate, bound
    seen, out = set(), []
    for lineno, msg in sorted(problems, key=lambda p: p[0]):
        text = f"line {lineno}: {msg}{_snippet(lines, lineno)}"
        if text not in seen:
            seen.add(text)
            out.append(text)
    if len(out) > 20:
        out = out[:20] + [f"... and {len(out) - 20} more problems"]
    return out


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


class SandboxError(RuntimeError):
    """The sandbox worker cannot be started."""


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


def _rebuild_batch(desc: dict):
    from iarcs_env.floorplan import FloorPlan
    from iarcs_env.rooms import get_room
    from iarcs_env.scene import SceneBatch

    return SceneBatch(get_room(desc["room"]), torch.from_numpy(desc["labels"]),
                      torch.from_numpy(desc["translations"]), torch.from_numpy(desc["half_sizes"]),
                      torch.from_numpy(desc["yaws"]), [FloorPlan(np.asarray(v)) for v in desc["floors"]],
                      list(desc["ids"]))


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


def _worker_main(config_json: str) -> None:
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

    def run(fn, batch) -> dict:
        """Call the program on a batch; the reply dict."""
        scene = Scene(batch)
        state["running"] = True
        try:
            out = fn(scene)
            values = _to_values(out, batch.batch_size)
        finally:
            state["running"] = False
        values, nonfinite, clipped = _clamp(values, clamp)
        return {"ok": True, "values": values.tolist(), "nonfinite": nonfinite, "clipped": clipped}

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
            return run(program[0], _rebuild_batch(msg["batch"]))
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
                [sys.executable, "-c", "import sys; from rewards.sandbox import _worker_main; "
                 "_worker_main(sys.argv[1])", json.dumps(config)],
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

    def score(self, batch) -> ScoreResult:
        """Run the active program on a SceneBatch. On failure ``ok`` is False, ``values`` are zeros and
        ``message`` says why (error, timeout, crash); the program stays loaded."""
        b = batch.batch_size
        zeros = np.zeros(b, dtype=np.float64)
        if self.code is None:
            return ScoreResult(zeros, False, "no reward program is loaded")
        t = time.monotonic()
        with self._lock:
            try:
                reply = self._request({"op": "score", "batch": describe_batch(batch)})
            except _WorkerLost as err:
                return ScoreResult(zeros, False, f"reward(scene) failed on a batch of {b} scenes: the sandbox "
                                   f"worker {err}; it was restarted", seconds=time.monotonic() - t)
        seconds = time.monotonic() - t
        output = str(reply.get("output", ""))[:MAX_PRINT_CHARS + 200]
        if not reply.get("ok"):
            return ScoreResult(zeros, False, str(reply.get("message", "unknown error"))[:4000], seconds=seconds,
                               output=output)
        try:
            values = np.asarray(reply["values"], dtype=np.float64).reshape(-1)
        except (KeyError, TypeError, ValueError):
            values = np.zeros(0)
        if values.shape != (b,):
            with self._lock:
                self._kill()  # the protocol cannot be trusted any more: start afresh next time
            return ScoreResult(zeros, False, f"the sandbox worker returned {values.size} values for {b} scenes",
                               seconds=seconds, output=output)
        values, extra_nonfinite, extra_clipped = _clamp(values, self.clamp)  # never trust the worker
        nonfinite = int(reply.get("nonfinite", 0)) + extra_nonfinite
        clipped = int(reply.get("clipped", 0)) + extra_clipped
        notes = []
        if nonfinite:
            notes.append(f"{nonfinite} of {b} values were NaN/inf (NaN -> 0, +-inf -> +-{self.clamp:g})")
        if clipped:
            notes.append(f"{clipped} of {b} values were beyond +-{self.clamp:g} and were clipped")
        return ScoreResult(values, True, "; ".join(notes), nonfinite, clipped, seconds, output)

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

    def __call__(self, batch) -> torch.Tensor:
        result = self.sandbox.score(batch)
        self.calls += 1
        self.seconds += result.seconds
        self.nonfinite += result.nonfinite
        if not result.ok:
            self.failures += 1
            self._record(f"batch {self.calls}: {result.message}")
        elif result.message:
            self._record(f"batch {self.calls}: {result.message}")
        return torch.as_tensor(result.values, dtype=torch.float32, device=batch.labels.device)

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

"""Layer 1 of the reward sandbox (:mod:`rewards.sandbox`): the static check of a reward program's source.

:func:`check_program` reads the program's syntax tree and refuses, with messages meant to be sent back to the LLM:
imports other than ``math``/``torch``, any name or attribute starting with ``_`` (a bare ``_`` is allowed), the
builtins that reach outside (open, eval, exec, getattr, globals, ...), attributes through which torch or numpy reach
the system or files (``torch.os``, ``torch.load``, ``torch.hub``, ``torch.utils``, ``x.numpy()``, ``a.tofile``,
frame and generator internals such as ``gi_frame``, ``str.format`` ...), ``match`` class patterns (they read
attributes), attribute assignment, classes, ``global``, and top-level statements other than imports, constant
assignments and function definitions (so loading runs nothing but definitions). A friendly first filter: the kernel
confines the worker whatever gets past it (:mod:`rewards.confine`).
"""

from __future__ import annotations

import ast

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
#: Attribute prefixes of frames, code objects, generators, coroutines and tracebacks.
FORBIDDEN_ATTRIBUTE_PREFIXES = ("f_", "gi_", "cr_", "ag_", "tb_", "co_", "im_", "func_")

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

